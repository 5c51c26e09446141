"""Fig. S9 summary: aberration estimation and reconstruction fidelity against the aberration RMS.

    python reproduce/figS9_summary.py --experiment figS9_quick [--tracking-uri sqlite:///mlflow.db]

The recipe is :func:`fgat.app.recipes.figS9_summary.main`; ``--help`` lists its options.
"""

from fgat.app.recipes.figS9_summary import main

if __name__ == "__main__":
    main()
