"""Which Prefect task runner a flow uses: a local pool by default, Dask at an address.

The nightly and rerun flows call :func:`default_task_runner` / :func:`make_task_runner`; the
choice of pool (and its size) lives here so that the flows stay orchestration only."""
from __future__ import annotations

import os

from prefect.task_runners import ThreadPoolTaskRunner

LOCAL_WORKERS = 2
DASK_ENV = "MIMUCAL_DASK_ADDRESS"  # the served deployment reads its Dask address here


def make_task_runner(dask_address: str | None = None, max_workers: int = LOCAL_WORKERS):
    if dask_address:
        from prefect_dask import DaskTaskRunner
        return DaskTaskRunner(address=dask_address)
    return ThreadPoolTaskRunner(max_workers=max_workers)


def default_task_runner():
    address = os.environ.get(DASK_ENV)
    return make_task_runner(address) if address else ThreadPoolTaskRunner(max_workers=LOCAL_WORKERS)
