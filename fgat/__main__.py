"""``python -m fgat``."""

from fgat.app.cli import run_command_line

run_command_line()
