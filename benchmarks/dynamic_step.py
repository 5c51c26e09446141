"""Benchmark one dynamic-stage frame-iteration (Note S7.2): deformation, voxelize, full step.

    python benchmarks/dynamic_step.py [--quick] [--repeats 5] [--profile 5]
        [--out benchmarks/results/dynamic_step.json]

The benchmark is :func:`fgat.app.recipes.dynamic_step.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.dynamic_step import main

if __name__ == "__main__":
    main()
