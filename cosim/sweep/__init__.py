"""Convergence sweeps: the sample generator and one row per run (`spec`), the Dask driver and results files
(`runner`), and the report (`report`). See SWEEP.md."""
