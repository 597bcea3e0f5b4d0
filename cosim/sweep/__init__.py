"""Convergence sweeps: the sample generator and one row per run (`spec`), the Dask driver and results files
(`runner`), and the report (`report`). How to run a sweep, the results file and the report: docs/guide/sweeps.md."""
