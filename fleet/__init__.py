"""A fleet of robots: batch identification on Dask, the fleet table and drift tracking.

- :mod:`.campaign`: a campaign TOML, or a folder/glob of logs, turned into tasks;
- :mod:`.storage`: fsspec locations (local folders by default), atomic result files;
- :mod:`.task`: one identification, as a Dask worker runs it (idempotent);
- :mod:`.engine`: the tasks on a ``LocalCluster`` or an existing scheduler, retries, progress;
- :mod:`.table`: the fleet table (Parquet, CSV), one row per robot and campaign;
- :mod:`.drift`: each robot's parameters against its baseline campaign in σ units, plots;
- :mod:`.commands`: ``drivegain batch``.
"""
