"""Fig. 3j: apparent tubule widths of SHB, 3DGAT, SHB with the 4DGAT-estimated PSF and 4DGAT
under aberrations, on a tubule phantom of known diameter.

    python reproduce/fig3j.py --quick [--seed 0] [--out DIR] [--tracking-uri sqlite:///mlflow.db]

The recipe is :func:`fgat.app.recipes.fig3j.main`; ``--help`` lists its options.
"""

from fgat.app.process import run_recipe
from fgat.app.recipes.fig3j import main

if __name__ == "__main__":
    run_recipe(main, "fig3j")
