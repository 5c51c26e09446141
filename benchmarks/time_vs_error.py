"""Run time against error: which method gets how close, how soon?

    python benchmarks/time_vs_error.py [--quick | --paper] [--phantom P ...] [--settings S ...]
        [--seed N] [--steps N] [--device auto] [--out benchmarks/results/time_vs_error]
    python benchmarks/time_vs_error.py --merge JSON [JSON ...] --out DIR

The benchmark is :func:`fgat.app.recipes.time_vs_error.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.time_vs_error import main

if __name__ == "__main__":
    main()
