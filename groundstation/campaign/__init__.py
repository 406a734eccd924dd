"""A test campaign: every flight of a set of logs identified and diagnosed the same way, in one table.

* :mod:`~groundstation.campaign.job` - one log analysed (read, prepare, identify, diagnose, cross-flight
  fit) into table rows; the unit of work a process pool or a Dask worker runs;
* :mod:`~groundstation.campaign.runner` - runs the jobs in-process, on a local process pool or on a
  Dask distributed cluster, handing each result back as it completes;
* :mod:`~groundstation.campaign.store` - the per-aircraft table in SQLite (and Parquet), the content
  hash that lets a re-run skip what is done, and the series the trend test reads;
* :mod:`~groundstation.campaign.plots` - trends as PNG and as a Rerun recording.

The numbers are the other packages' (``sysid``, ``gap``, ``trends``); this package only chains them,
distributes the work and stores the results.
"""
