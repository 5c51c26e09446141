"""JPGM from zero against the true volume: does the estimate reach the true coefficients?

    python benchmarks/jpgm_basin.py [--amplitude 1.0] [--seed 0] [--steps 400]
        [--out benchmarks/results/jpgm_basin.json]

The benchmark is :func:`fgat.app.recipes.jpgm_basin.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.jpgm_basin import main

if __name__ == "__main__":
    main()
