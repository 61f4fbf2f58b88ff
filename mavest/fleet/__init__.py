"""``mavest fleet``: every log of a folder or a bucket replayed, one table, on Dask.

* :mod:`mavest.fleet.inputs`: the arguments (paths, folders, globs, fsspec URLs) as
  the list of logs, in order; each log's name for its own outputs;
* :mod:`mavest.fleet.rows`: one log → its rows (``mavest replay`` of it, summed up),
  what a worker runs; never raises for a bad log;
* :mod:`mavest.fleet.cluster`: the logs on a LocalCluster or an existing cluster
  (needs ``mavest[fleet]``: dask.distributed);
* :mod:`mavest.fleet.table`: the rows as Parquet or CSV, written whole.

Only :mod:`~mavest.fleet.cluster` imports Dask.
"""
