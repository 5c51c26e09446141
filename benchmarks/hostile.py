"""Hostile inputs over every command: each case ends in one clean refusal before any
computation, a warning, or a result that is right (``tests/integration/test_hostile.py`` runs the
same table in-process). The cases that start from a shipped config read it from the repository's
``configs/`` folder.

    python benchmarks/hostile.py [--only ID ...] [--timeout 60] \\
        [--out benchmarks/results/hostile.json]
    python benchmarks/hostile.py --table benchmarks/results/hostile.json
    python benchmarks/hostile.py --compare benchmarks/results/hostile_before.json \\
        --table benchmarks/results/hostile.json

The benchmark is :func:`fgat.app.recipes.hostile.main`; ``--help`` lists its options.
"""

from pathlib import Path

from fgat.app.recipes.hostile import main

if __name__ == "__main__":
    main(Path(__file__).resolve().parents[1] / "configs")
