"""Studies at scale: thousands to millions of simulated runs of the controller over noise, latency,
lag, team size, gains and starts, on Dask (an embedded LocalCluster by default, a scheduler's
address for a cluster), with results in Parquet, resume, and Optuna for ``[optimize]``.

The study file's reading, the points and the point function are pure (core.study); here: the
engine (engine.py, optimize.py), what a worker runs (batch.py), the folder (store.py), the summary
and plots (summary.py), and the session that ties them (session.py). docs/studies.md says how to
use it.
"""
