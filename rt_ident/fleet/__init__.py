"""The fleet: many axes' recordings identified on Dask, kept as a Parquet history, checked for drift.

* :mod:`~rt_ident.fleet.manifest` - the CSV listing recordings (path, machine, axis, time);
* :mod:`~rt_ident.fleet.identify` - one Dask task per recording, results appended to the history;
* :mod:`~rt_ident.fleet.history` - DuckDB over the history's Parquet files, read-only;
* :mod:`~rt_ident.fleet.store` - the history's files: damaged ones skipped, whole-file writes, the lock;
* :mod:`~rt_ident.fleet.drift` - each series' state, from CUSUM alarms per machine, axis and parameter;
* :mod:`~rt_ident.fleet.findings` - what an alarm means on the machine (the rules table) and how urgent it is;
* :mod:`~rt_ident.fleet.report` - one HTML page (the fleet worst first, trends, findings) and its CSV data;
* :mod:`~rt_ident.fleet.paths` - file names from machine and axis names, kept inside the output folder;
* :mod:`~rt_ident.fleet.make` - a generated fleet to try it on.
"""
