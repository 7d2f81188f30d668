"""Where tasks run: the embedded thread pool, a LocalCluster, or an existing cluster.

The engine only needs one operation, ``map_unordered``: run a function over many small
argument tuples and hand back the results as they complete, so that the client can add
mesh-sized partial results into its totals (a streaming reduction) and count progress.

Both runners forget each result once it has been handed over. The ``M`` pass's partials
are 1.4 MB per block (float64 stencil of 9³ nodes), 5.8 GB over the 4096 blocks of a
level-0 2048³ run with ``ell = 16``; keeping the finished futures until the end of the
pass held them all, 3 GB on each of two workers.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from . import config
from .errors import InputError

log = logging.getLogger(__name__)

#: ``--scheduler`` help of every CLI command that computes
SCHEDULER_HELP = ("where tasks run: threads (default, this process), local[:N] (a LocalCluster of N workers "
                  "on loopback), or the address of an existing scheduler (tcp://host:8786, tls://...)")


class ThreadRunner:
    """Embedded default: a pool of threads in this process (no cluster to set up).

    The numba kernels release the GIL, and Zarr decompression does too, so threads give
    real parallelism, like Dask's threaded scheduler.
    """

    def __init__(self, n_threads: int | None = None):
        self.n_workers = n_threads or config.get("num-threads") or os.cpu_count() or 1
        self._pool = concurrent.futures.ThreadPoolExecutor(self.n_workers)
        self.dashboard_link = None
        self.local = True  # tasks run on this machine

    def map_unordered(self, fn: Callable, args: Iterable[tuple]) -> Iterator[Any]:
        # Each result is handed over and forgotten (module docstring).
        pending = {self._pool.submit(fn, *a) for a in args}
        try:
            for fut in concurrent.futures.as_completed(pending):
                pending.discard(fut)
                result = fut.result()
                del fut
                yield result
        finally:
            for fut in pending:
                fut.cancel()

    def run_everywhere(self, fn: Callable) -> None:
        fn()

    def close(self) -> None:
        self._pool.shutdown(cancel_futures=True)

    def __repr__(self) -> str:
        return f"embedded thread pool ({self.n_workers} threads)"


class DistributedRunner:
    """Tasks on a ``dask.distributed`` cluster through a ``Client``.

    Each task receives paths, a block description and its own slice of the nodal
    field (kilobytes), never voxels; results are mesh-sized partials.
    """

    def __init__(self, client, cluster=None):
        self.client = client
        self._cluster = cluster
        self.dashboard_link = getattr(client, "dashboard_link", None)
        info = client.scheduler_info()
        # Tasks run on this machine (so scratch arrays may be memory-mapped files) when we
        # started the cluster, or when its scheduler and every worker listen on loopback
        # (a worker elsewhere could not reach a loopback scheduler); otherwise they may
        # span hosts.
        self.local = cluster is not None or all(
            _on_loopback(a) for a in [client.scheduler.address, *info["workers"]])
        self.n_workers = max(1, sum(w.get("nthreads", 1) for w in info["workers"].values()))

    def map_unordered(self, fn: Callable, args: Iterable[tuple]) -> Iterator[Any]:
        from distributed import as_completed

        args = list(args)
        if not args:
            return
        import dask

        # Each task carries its own slice of the nodal field: at 128³ nodes a pass's graph
        # is ~70 MB, sent once per pass, which the client has to send anyway. distributed
        # would warn about it (above 10 MB) on every pass.
        with dask.config.set({"distributed.admin.large-graph-warning-threshold": "2GB"}):
            futures = self.client.map(fn, *zip(*args), pure=False)
        # Each result is released on the workers as soon as it is received (module docstring).
        pending = set(futures)
        done = as_completed(futures, with_results=True)
        del futures
        try:
            for fut, result in done:
                pending.discard(fut)
                fut.release()
                del fut
                yield result
        finally:
            self.client.cancel(list(pending))

    def run_everywhere(self, fn: Callable) -> None:
        self.client.run(fn)

    def close(self) -> None:
        if self._cluster is not None:
            self.client.close()
            self._cluster.close()

    def __repr__(self) -> str:
        return f"dask.distributed cluster ({self.n_workers} threads), dashboard {self.dashboard_link}"


def _on_loopback(address: str) -> bool:
    """Whether a Dask address (``tcp://127.0.0.1:8786``, ``inproc://…``) is on this host only."""
    import ipaddress
    from urllib.parse import urlparse

    if address.startswith("inproc://"):
        return True
    host = urlparse(address).hostname or ""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def start_local_cluster(n_workers: int | None = None, threads_per_worker: int = 1):
    """Start a ``LocalCluster`` that listens on loopback only (scheduler, workers, dashboard)."""
    from distributed import Client, LocalCluster

    n = n_workers or os.cpu_count() or 1
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=threads_per_worker,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
        processes=True,
    )
    return Client(cluster), cluster


@contextlib.contextmanager
def open_runner(scheduler=None):
    """Context manager giving a runner for ``scheduler``.

    Parameters
    ----------
    scheduler : None, "threads", "local", "local:N", address string, or distributed.Client
        ``None``/``"threads"``: embedded thread pool (default). ``"local"`` or
        ``"local:N"``: a LocalCluster of N single-threaded worker processes on loopback,
        started and stopped here. ``"tcp://host:port"`` (or ``tls://…``): an existing
        scheduler. A ``distributed.Client``: used as is and left open.
    """
    if scheduler is None or scheduler == "threads":
        runner = ThreadRunner()
    elif isinstance(scheduler, str) and scheduler.startswith("local"):
        _, _, n = scheduler.partition(":")
        try:
            n_workers = int(n) if n else None
        except ValueError:
            raise InputError(f"scheduler {scheduler!r}: expected 'local' or 'local:N'") from None
        client, cluster = start_local_cluster(n_workers)
        runner = DistributedRunner(client, cluster)
    elif isinstance(scheduler, str):
        from distributed import Client

        if "://" not in scheduler:
            raise InputError(
                f"scheduler {scheduler!r}: expected 'threads', 'local[:N]' or an address like tcp://host:8786"
            )
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach scheduler {scheduler}: {exc}") from None
        except (TypeError, ValueError) as exc:  # e.g. tls:// without certificates configured
            raise InputError(
                f"cannot connect to {scheduler} ({exc}); for tls:// set distributed.comm.tls.* "
                "(see docs/distributed.md)"
            ) from None
        runner = DistributedRunner(client, cluster=None)
        runner._owns_client = True
    else:
        runner = DistributedRunner(scheduler)
    log.info("running on %r", runner)
    try:
        yield runner
    finally:
        if getattr(runner, "_owns_client", False):
            runner.client.close()
        runner.close()


@contextlib.contextmanager
def dask_scheduler(scheduler=None, announce: Callable[[str], None] | None = None):
    """Context manager running the ``dask`` collections computed inside it on ``scheduler``.

    For the Dask-array steps (ingest, pyramid, synthesis): ``None``/``"threads"`` keeps
    dask's default (chunkdic's embedded thread pool); anything else is opened with
    :func:`open_runner` and its client made the current one, so the chunk writes run on its
    workers (which must see the same file system as the client). ``announce`` receives one
    line naming the cluster and its dashboard.
    """
    if scheduler is None or scheduler == "threads":
        yield None
        return
    with open_runner(scheduler) as runner:
        if announce is not None:
            announce(f"running on {runner!r}")
        with runner.client.as_current():
            yield runner
