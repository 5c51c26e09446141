"""What the recipes (``reproduce/``), the benchmarks (``benchmarks/``) and the tests share.

The scripts in ``reproduce/`` and ``benchmarks/`` parse their command line and call a function
here; the tests call the same functions. The repository's folders that the recipes read or
write (``configs/``, ``reproduce/systems/``, ``reproduce/results/``) are given by the scripts,
relative to themselves or to the working directory, never found from this package's location.

Modules
-------
benchmark
    Timing, the benchmarks' common options, result files with their provenance.
optics, figS9_summary, figS10
    Figs. S5-S10: the optics self-estimation recipes and their MLflow summaries.
fig3j, flfm_phantoms, fig5_tracking, fig5_cytometry, highna_shell
    Fig. 3j, Fig. 5 and the high-NA recipe on phantoms with a known answer.
time_vs_error, optics_trial, jpgm_basin, dynamic_step, stress, hostile
    The benchmarks that tests and other benchmarks call into.
"""
