"""``python -m fgat``."""

from fgat.cli import run_command_line

run_command_line()
