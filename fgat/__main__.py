"""``python -m fgat``."""

import sys

from fgat.cli import main

sys.exit(main())
