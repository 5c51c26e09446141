"""Time one 4DGAT trial of an optics figure end to end, with sigma after every JPGM event.

    python benchmarks/optics_trial.py [--figure figS6] [--quick] [--seed N] [--depth-chunk N]
        [--tolerance T --parameter-tolerance P] [--amplitude A] [--blur-px 4,2,1,0
        --blur-events N] [--start N --every N --steps N] [--max-steps N] [--event-psnr]
        [--out benchmarks/results/optics_trial.json]

The benchmark is :func:`fgat.app.recipes.optics_trial.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.optics_trial import main

if __name__ == "__main__":
    main()
