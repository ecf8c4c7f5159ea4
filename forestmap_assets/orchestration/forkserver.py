"""The fork server of the worker processes, started as early as possible (issue 16).

``forestmap run`` runs scans and pairs in worker processes forked from a fork server (a fork of
the main process could inherit its OpenMP threads). Forked workers inherit what the server
imported. The server therefore preloads :mod:`.worker_libraries`: Dagster and forestmap, Open3D,
SciPy's k-d trees, Dagster's SQLite storage and numba's CPU target. It is started from the
command line before the main process imports anything heavy, so the two processes import side
by side. This module itself imports only :mod:`multiprocessing`."""

from __future__ import annotations

import multiprocessing

PRELOAD = ["forestmap_assets.orchestration.worker_libraries"]


def context():
    """The ``forkserver`` start context with :data:`PRELOAD` set (before the server starts)."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


def start() -> None:
    """Start the fork server now, in the background (a no-op when it is running)."""
    from multiprocessing import forkserver

    context()
    forkserver.ensure_running()
