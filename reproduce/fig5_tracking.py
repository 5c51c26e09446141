"""Fig. 5h-j on a phantom with a known answer: speed classes and anomalous diffusion of cells.
Results go to ``reproduce/results/fig5_tracking[_quick]`` unless ``--out`` says otherwise.

    python reproduce/fig5_tracking.py [--quick] [--seed N] [--out DIR]

The recipe is :func:`fgat.app.recipes.fig5_tracking.main`; ``--help`` lists its options.
"""

from pathlib import Path

from fgat.app.recipes.fig5_tracking import main

if __name__ == "__main__":
    main(Path(__file__).resolve().parent / "results")
