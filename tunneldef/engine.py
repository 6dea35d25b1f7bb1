"""Dask as the engine that runs independent tasks (the chainage tiles of :mod:`.tiles`).

Three ways to run, chosen by :func:`open_engine`:

* default: Dask's local threaded scheduler, sized to the machine (tasks release the GIL in
  NumPy, SciPy and Open3D);
* ``workers=N``: a ``dask.distributed.LocalCluster`` of ``N`` single-threaded worker
  processes on 127.0.0.1;
* ``scheduler="tcp://host:port"``: an existing ``dask.distributed`` cluster.

Tasks receive paths and small parameters only, never point arrays: the points travel through
a folder every worker can read (:mod:`.tiles`). A worker that dies is replaced by the
scheduler and its task run again; a task that cannot be completed stops the run with a one-line
:class:`EngineError`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from typing import Any

from .errors import TunnelDefError
from .progress import ProgressCallback, notify

__all__ = [
    "Engine", "EngineError", "open_engine", "release_memory", "limit_malloc_arenas", "thread_map",
]

logger = logging.getLogger(__name__)

#: A task is run again this many times after an exception in it (a lost worker is handled by
#: the scheduler itself, up to ``distributed.scheduler.allowed-failures`` times).
RETRIES = 2


def _glibc() -> Any:
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:  # not glibc (musl, ...)
        return None


def release_memory() -> None:
    """Give the heap's free pages back to the operating system (glibc ``malloc_trim(0)``;
    nothing elsewhere).

    A tile's arrays are freed when its task ends, but glibc keeps the pages in its arenas,
    one per thread that allocated, so the process grows tile after tile although its live
    data do not; Dask's own advice for workers ("memory not released back to the OS") is
    this call. Worker processes started by a Dask nanny trim by themselves (it sets
    ``MALLOC_TRIM_THRESHOLD_``, ``distributed.nanny.pre-spawn-environ``); the local scheduler
    calls this after every task.
    """
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


def limit_malloc_arenas(arenas: int = 2) -> None:
    """Let glibc create at most ``arenas`` malloc arenas from now on (``mallopt``
    ``M_ARENA_MAX``; nothing elsewhere): each thread of NumPy, SciPy, Open3D and Dask would
    otherwise get its own, and freed memory in one cannot serve another. On a 100 m survey
    (4.6 M points per epoch) this lowered the peak from 3.09 to 2.80 GB at the same speed.
    """
    libc = _glibc()
    if libc is not None:
        libc.mallopt(-8, int(arenas))  # M_ARENA_MAX


def thread_map(
    fn: Callable[..., Any],
    args: Sequence[tuple[Any, ...]],
    *,
    threads: int | None = None,
    stage: str = "",
    progress: ProgressCallback | None = None,
    after_task: Callable[[], None] | None = None,
) -> list[Any]:
    """``[fn(*a) for a in args]`` on Dask's local threaded scheduler, results in order.

    For independent pieces of one process that spend their time in compiled code that
    releases the GIL (NumPy, SciPy, scikit-image, the Numba kernels): a centreline pass's
    slices, the registration's direction candidates, the registration check's slides; and
    the chainage tiles on the local scheduler. ``threads`` defaults to the machine's cores;
    with one thread, or one task, the tasks run in the calling thread, in order.
    ``progress(stage, fraction)`` is called from the calling thread as tasks finish;
    ``after_task`` after each task (e.g. :func:`release_memory`).
    """
    n = len(args)
    threads = max(int(threads if threads is not None else (os.cpu_count() or 1)), 1)
    if threads == 1 or n <= 1:
        out = []
        for i, a in enumerate(args):
            out.append(fn(*a))
            if after_task is not None:
                after_task()
            notify(progress, stage, (i + 1) / max(n, 1))
        return out
    import dask
    import dask.threaded
    from dask.callbacks import Callback

    tasks = [dask.delayed(fn, pure=False)(*a) for a in args]
    state = {"done": 0}

    def posttask(key, result, dsk, state_, worker_id):  # noqa: ARG001
        if after_task is not None:
            after_task()
        state["done"] += 1
        notify(progress, stage, min(state["done"] / n, 1.0))

    with Callback(posttask=posttask):
        # Dask's threaded scheduler given as the function itself: named as "threads", Dask
        # first imports ``distributed`` to look for a client (0.5 s of every run's start)
        return list(dask.compute(*tasks, scheduler=dask.threaded.get, num_workers=threads))


class EngineError(TunnelDefError):
    """A task failed on the cluster (or the cluster was lost) and the run was stopped."""


class Engine:
    """Runs a function over many argument tuples and returns the results in order.

    Parameters
    ----------
    client : dask.distributed.Client, optional
        A client of a distributed cluster; ``None`` runs on Dask's local threaded scheduler.
    threads : int
        Tasks at once on the local scheduler.
    cluster : object, optional
        The ``LocalCluster`` this engine started (closed by :meth:`close`).
    tile_memory_gb : float
        Working memory one task may take, GB.
    """

    def __init__(
        self, client: Any = None, threads: int = 1, cluster: Any = None,
        tile_memory_gb: float = 1.0,
    ) -> None:
        self.client = client
        self.threads = max(int(threads), 1)
        self._cluster = cluster
        self.tile_memory_gb = float(tile_memory_gb)

    @property
    def distributed(self) -> bool:
        """True when tasks run on worker processes (they may be on other machines)."""
        return self.client is not None

    def map(
        self,
        fn: Callable[..., Any],
        args: Sequence[tuple[Any, ...]],
        *,
        stage: str,
        progress: ProgressCallback | None = None,
    ) -> list[Any]:
        """``[fn(*a) for a in args]``, run as Dask tasks.

        Raises
        ------
        EngineError
            When a task fails after its retries or its worker was lost too often.
        """
        notify(progress, stage, 0.0)
        n = len(args)
        if n == 0:
            return []
        if self.client is None:
            return self._map_local(fn, args, stage, progress)
        from distributed import as_completed

        futures = [self.client.submit(fn, *a, pure=False, retries=RETRIES) for a in args]
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[Any] = [None] * n
        done = 0
        try:
            for fut in as_completed(futures):
                out[index[fut.key]] = fut.result()
                done += 1
                notify(progress, stage, done / n)
        except TunnelDefError:
            raise
        except Exception as exc:  # KilledWorker, CommClosedError, a task's own error
            for f in futures:
                f.cancel()
            raise EngineError(f"{stage}: {_one_line(exc)}") from exc
        return out

    def _map_local(self, fn, args, stage, progress):
        return thread_map(fn, args, threads=self.threads, stage=stage, progress=progress,
                          after_task=release_memory)

    def close(self) -> None:
        """Close the client and any cluster this engine started."""
        if self.client is not None:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if type(exc).__name__ not in text else text


#: Working memory below which a tile is not worth running beside another one, GB (smaller
#: tiles spend more of their points on margins).
MIN_TILE_MEMORY_GB = 1.5


def open_engine(
    *, scheduler: str | None = None, workers: int | None = None, threads: int | None = None,
    memory_gb: float = 1.5,
) -> Engine:
    """The engine for a run.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing ``dask.distributed`` scheduler (``tcp://host:port``).
    workers : int, optional
        Start a ``LocalCluster`` of this many single-threaded worker processes on 127.0.0.1.
    threads : int, optional
        Tasks at once on the local threaded scheduler (default: the machine's cores, as many
        as ``memory_gb`` holds at ``MIN_TILE_MEMORY_GB`` each).
    memory_gb : float
        Working memory of the tasks, GB: on the local scheduler for all running at once
        (each gets its share), on a cluster for each worker's task.

    Raises
    ------
    EngineError
        If the scheduler cannot be reached, or both ``scheduler`` and ``workers`` are given.
    """
    if scheduler and workers:
        raise EngineError("give either --scheduler or --workers, not both")
    if scheduler:
        from distributed import Client

        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise EngineError(f"cannot reach the Dask scheduler at {scheduler}: "
                              f"{_one_line(exc)}") from exc
        logger.info("Dask cluster %s: %d workers; dashboard %s", scheduler,
                    len(client.scheduler_info().get("workers", {})), client.dashboard_link)
        return Engine(client, tile_memory_gb=memory_gb)
    if workers:
        if int(workers) < 1:
            raise EngineError(f"--workers must be at least 1, got {workers}")
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)
        logger.info("Dask LocalCluster: %d worker processes", int(workers))
        return Engine(client, cluster=cluster, tile_memory_gb=memory_gb)
    if threads is None:
        threads = min(os.cpu_count() or 1, max(1, int(memory_gb / MIN_TILE_MEMORY_GB)))
    return Engine(None, threads, tile_memory_gb=memory_gb / threads)
