"""Figs. S5-S8: JPGM self-estimation of the optics, 4DGAT against 3DGAT and SHB.

    python reproduce/optics.py figS6 --quick [--seeds 0 1 2] [--tracking-uri sqlite:///mlflow.db]

The recipe is :func:`fgat.app.recipes.optics.main`; ``--help`` lists its options.
"""

from fgat.app.process import run_recipe
from fgat.app.recipes.optics import main

if __name__ == "__main__":
    run_recipe(main, "reproduce/optics.py")
