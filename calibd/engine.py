"""The batch engine: tasks on Dask (`dask.distributed`), on a local cluster of worker processes
or on a cluster that already runs (a scheduler's address or its scheduler file).

Dask is the engine rather than a process pool of our own because a lab that outgrows one
machine may already run it, and because it brings what a long batch needs: a task whose worker
dies is given to another one, workers can join while it runs. Every worker has one BLAS thread
(Dask's own default for the processes it starts): the same task then gives the same bits on any
worker, and two processes on two cores do not fight over them. `calibd batch` and the Monte
Carlo benchmarks use it alike.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .errors import CalibdError

NEEDS_EXTRA = "the batch engine needs the fleet extra: pip install 'stim300-calib[fleet]'"
CONNECT_TIMEOUT_S = 10
SCHEDULER_FILE_LIMIT = 1 << 20  # bytes: a scheduler file is a few hundred
RETRIES = 2  # a task that raised is tried again this often (its worker died: Dask gives it to another one anyway)


class EngineError(CalibdError):
    """A cluster that cannot be reached or started; one line."""


@dataclass(frozen=True)
class TaskFailed:
    """What `run_tasks` yields for a task that raised on every try, or whose workers kept dying:
    `reason` in one line (a value in the results, never raised)."""

    reason: str


def _distributed():
    try:
        import distributed
    except ImportError:
        raise EngineError(NEEDS_EXTRA) from None
    return distributed


@contextmanager
def cluster(scheduler: str | None = None, workers: int | None = None):
    """A Dask client: connected to `scheduler` (tcp://HOST:PORT, or the path of a scheduler file
    that `dask scheduler --scheduler-file` wrote), or to a local cluster of `workers` processes
    (default: one per core) that ends with the block."""
    distributed = _distributed()
    if scheduler is None:
        count = workers or os.cpu_count() or 1
        try:
            local = distributed.LocalCluster(n_workers=count, threads_per_worker=1, processes=True,
                                             dashboard_address=None, silence_logs=logging.ERROR)
        except OSError as exc:
            raise EngineError(f"cannot start {count} local Dask workers: {exc}") from None
        with local, distributed.Client(local) as client:
            yield client
        return
    address = _scheduler_address(scheduler) if Path(scheduler).is_file() else scheduler
    try:
        client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise EngineError(f"--scheduler {scheduler}: cannot connect: {reason[:160]}") from None
    with client:
        yield client


def _scheduler_address(path: str) -> str:
    """The address in a scheduler file (JSON that `dask scheduler --scheduler-file` writes)."""
    from stim300.cliutil import read_input
    from stim300.errors import UsageError

    try:
        address = json.loads(read_input(path, "scheduler file", SCHEDULER_FILE_LIMIT)).get("address")
    except UsageError as exc:
        raise EngineError(f"--scheduler {exc}") from None
    except (ValueError, AttributeError) as exc:
        raise EngineError(f"--scheduler {path}: not a Dask scheduler file ({type(exc).__name__})") from None
    if not isinstance(address, str):
        raise EngineError(f"--scheduler {path}: not a Dask scheduler file (no address in it)")
    return address


def run_tasks(client, function: Callable, items: Iterable, names: Iterable[str] | None = None) -> Iterator:
    """`function(item)` for every item on the cluster, yielded as (index, result) in the order
    they finish; a task that failed for good yields (index, TaskFailed). `names`: each task's
    name on the cluster (its dashboard shows them)."""
    distributed = _distributed()
    items = list(items)
    keys = list(names) if names is not None else [f"task-{k}" for k in range(len(items))]
    run = secrets.token_hex(4)  # a cluster may run several batches: each task's key is its own
    futures = {client.submit(function, item, key=f"{key}-{run}", retries=RETRIES, pure=False): k
               for k, (item, key) in enumerate(zip(items, keys))}
    for future in distributed.as_completed(futures):
        index = futures.pop(future)
        try:
            yield index, future.result()
        except distributed.KilledWorker:
            yield index, TaskFailed("every worker that ran it died (out of memory?)")
        except Exception as exc:  # noqa: BLE001 (a task's own error, raised on its last try, is its row)
            yield index, TaskFailed(f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}")
        finally:
            future.release()
