"""The high-NA recipe's steps in Python (run by ``reproduce/highna_shell.sh``): the wrong
variants of its system ``reproduce/systems/highna37.yaml`` and the scores of its volumes.

    python reproduce/highna_shell.py systems OUT
    python reproduce/highna_shell.py summary OUT

The recipe is :func:`fgat.app.recipes.highna_shell.main`; ``--help`` lists its options.
"""

from pathlib import Path

from fgat.app.recipes.highna_shell import main

if __name__ == "__main__":
    main(Path(__file__).resolve().parent / "systems" / "highna37.yaml")
