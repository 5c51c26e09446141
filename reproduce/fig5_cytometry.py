"""Fig. 5e-g and Fig. S14 on a phantom with a known answer: volumetric cytometry of four
marker-defined cell classes. Results go to ``reproduce/results/fig5_cytometry[_quick]``
unless ``--out`` says otherwise.

    python reproduce/fig5_cytometry.py [--quick] [--seed N] [--out DIR]

The recipe is :func:`fgat.app.recipes.fig5_cytometry.main`; ``--help`` lists its options.
"""

from functools import partial
from pathlib import Path

from fgat.app.process import run_recipe
from fgat.app.recipes.fig5_cytometry import main

if __name__ == "__main__":
    run_recipe(partial(main, Path(__file__).resolve().parent / "results"), "fig5_cytometry")
