"""A fleet's logs, on one machine or many (``mavcal calibrate`` with several sources).

- :mod:`mavcal.fleet.inputs`: the logs as a fleet keeps them (directories, globs, list files,
  fsspec URLs such as ``s3://bucket/prefix/``), and a log's content hash;
- :mod:`mavcal.fleet.table`: the results table (``--table results.csv`` / ``.parquet``), one
  row per log written as each log finishes, that a run killed and started again resumes;
- :mod:`mavcal.fleet.run`: the per-log jobs in the fork pool or on a Dask cluster
  (``--scheduler-address``), skipping the logs already in the table;
- :mod:`mavcal.fleet.progress`: the progress line on a terminal;
- :mod:`mavcal.fleet.drift`: drift over time per vehicle, from the table's rows.

Object storage and Dask need the optional extra ``mavcal[fleet]`` (dask[distributed], fsspec,
s3fs, pyarrow); local files, CSV tables and the fork pool need nothing beyond mavcal's own.
"""
