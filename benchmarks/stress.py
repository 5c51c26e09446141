"""Numerical stress table: each case ends finite within its stated tolerance, or is refused up
front with a clear message.

    python benchmarks/stress.py [--quick] [--out benchmarks/results/stress.json]

The benchmark is :func:`fgat.app.recipes.stress.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.stress import main

if __name__ == "__main__":
    main()
