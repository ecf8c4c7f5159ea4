"""The Dask cluster of a ``--executor dask`` run: the given scheduler, or a local cluster for the
session (dask is imported only when a run asks for it)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator


@contextlib.contextmanager
def dask_cluster(address: str | None, workers: int, progress: Callable[[str], None]) -> Iterator[str]:
    """The Dask scheduler address: ``address`` / ``$FORESTMAP_DASK_ADDRESS``, else a local
    cluster (one single-threaded worker process per core) for this session."""
    address = address or os.environ.get("FORESTMAP_DASK_ADDRESS")
    if address:
        yield address
        return
    try:
        from dask.distributed import LocalCluster
    except ImportError:
        raise ValueError(
            "--executor dask needs dask.distributed (pip install dagster-dask)"
        ) from None
    with LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        progress(f"  dask: local cluster {cluster.scheduler_address} with {workers} workers")
        yield cluster.scheduler_address
