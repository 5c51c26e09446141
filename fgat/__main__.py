"""``python -m fgat``."""

from fgat.cli import exit_without_finalising, main

exit_without_finalising(main())
