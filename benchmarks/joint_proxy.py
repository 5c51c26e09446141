"""Fig. S7's joint estimation on a CPU proxy of the paper's scale.

The benchmark is :mod:`fgat.app.recipes.joint_proxy`; ``--help`` lists its options.
"""

from fgat.app.recipes.joint_proxy import main

if __name__ == "__main__":
    main()
