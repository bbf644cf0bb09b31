"""Studies: Monte Carlo robustness, identification and design sweeps of many headless twins on Dask (issue 19).

spec (what varies, the runs), run (one run, pure and picklable), execute (Dask tasks → Parquet,
resumable), report (summary JSON and figures). ``xneck study`` and ``/api/studies`` use them.
"""
