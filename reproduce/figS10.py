"""Fig. S10: Zernike-coefficient trajectories of one Fig. S9 trial during the static stage.

    python reproduce/figS10.py [--quick] [--experiment figS9] [--run rms1.0-seed0]

The recipe is :func:`fgat.app.recipes.figS10.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.figS10 import main

if __name__ == "__main__":
    main()
