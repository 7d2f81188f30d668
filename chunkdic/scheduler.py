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
import ctypes
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from . import config
from .errors import InputError, WorkerLostError

log = logging.getLogger(__name__)

#: ``--scheduler`` help of every CLI command that computes
SCHEDULER_HELP = ("where tasks run: threads (default, this process), local[:N] (a LocalCluster of N workers "
                  "on loopback), or the address of an existing scheduler (tcp://host:8786, tls://...)")


#: tasks per thread the embedded pool has submitted ahead of the results handed over
WINDOW = 4


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
        """Results as they complete; at most :data:`WINDOW` tasks per thread submitted ahead.

        ``args`` is consumed as tasks are submitted: a generator of arguments (the engine's
        passes slice each block's nodal field as its task is submitted) then holds only
        those of the window, not a pass's worth (70 MB at 128³ nodes, docs/distributed.md).
        """
        # Each result is handed over and forgotten (module docstring).
        todo = iter(args)
        window = WINDOW * self.n_workers
        pending: set = set()

        def submit() -> None:
            for a in todo:
                pending.add(self._pool.submit(fn, *a))
                if len(pending) >= window:
                    return

        try:
            submit()
            while pending:
                done, _ = concurrent.futures.wait(pending, return_when=concurrent.futures.FIRST_COMPLETED)
                pending -= done
                submit()  # the threads stay busy while the client adds the results up
                while done:
                    fut = done.pop()
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
            # a task whose worker dies is run again by the scheduler on another worker (up to
            # distributed.scheduler.allowed-failures times); only when it gives up, or when
            # the connection to the cluster is lost, does the run stop, in one line
            for fut, result in _stop_if_workers_lost(done):
                pending.discard(fut)
                fut.release()
                del fut
                yield result
        finally:
            self.client.cancel(list(pending))

    def run_everywhere(self, fn: Callable) -> None:
        """Run ``fn`` on every worker (the kernels' warm-up). A worker that died meanwhile (its
        nanny starts another, which compiles on its first task) is skipped; no live worker at
        all is :class:`WorkerLostError`; any other failure is raised as it is."""
        try:
            results = self.client.run(fn, on_error="return")
        except _lost_worker_errors() as exc:
            raise WorkerLostError(_lost_message(exc)) from None
        failed = {w: r for w, r in results.items() if isinstance(r, BaseException)}
        other = [r for r in failed.values() if not isinstance(r, _lost_worker_errors())]
        if other:
            raise other[0]
        if len(failed) == len(results):
            raise WorkerLostError(_lost_message(next(iter(failed.values()), None)))
        if failed:
            log.warning("%d of %d Dask workers died before this run started; continuing on the others",
                        len(failed), len(results))

    def close(self) -> None:
        if self._cluster is not None:
            self.client.close()
            self._cluster.close()

    def __repr__(self) -> str:
        return f"dask.distributed cluster ({self.n_workers} threads), dashboard {self.dashboard_link}"


def _lost_worker_errors() -> tuple[type, ...]:
    """The exceptions by which distributed says that workers died (imported lazily)."""
    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    return (KilledWorker, CommClosedError)


def _lost_message(exc) -> str:
    detail = str(exc).splitlines()[0] if exc is not None and str(exc) else ""
    detail = detail if len(detail) <= 120 else detail[:119] + "…"
    what = "" if exc is None else f" ({type(exc).__name__}{': ' + detail if detail else ''})"
    return (f"the Dask cluster lost the workers this run needs{what}: the run cannot continue; what it saved is "
            "kept (a checkpoint, complete steps): run the same command again to resume")


def _stop_if_workers_lost(results):
    try:
        yield from results
    except _lost_worker_errors() as exc:
        raise WorkerLostError(_lost_message(exc)) from None


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
    import dask.config
    from distributed import Client, LocalCluster

    n = n_workers or os.cpu_count() or 1
    preload = dask.config.get("distributed.worker.preload", [])
    preload = [preload] if isinstance(preload, str) else list(preload)
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=threads_per_worker,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
        processes=True,
        # a worker's own close is not an error (chunkdic.worker_setup); the user's preloads kept
        preload=[*preload, "chunkdic.worker_setup"],
    )
    return Client(cluster), cluster


def local_workers(scheduler: str) -> int | None:
    """The worker count of a ``"local:N"`` scheduler string (None without ``:N``)."""
    _, _, n = scheduler.partition(":")
    if not n:
        return None
    try:
        n_workers = int(n)
    except ValueError:
        raise InputError(f"scheduler {scheduler!r}: expected 'local' or 'local:N'") from None
    if n_workers < 1:
        raise InputError(f"scheduler {scheduler!r}: a local cluster needs at least one worker (local:N, N >= 1)")
    return n_workers


def probe_scheduler(address: str, timeout: float | None = None) -> None:
    """Refuse, within ``timeout`` seconds, an address where no Dask scheduler answers.

    A Dask scheduler sends its handshake as soon as a connection opens: an 8-byte frame
    length (tens of bytes). ``distributed`` itself waits for it with no time limit (an
    HTTP server, which waits for a request, hangs it for ever) and trusts the length (the
    first 8 bytes of another protocol's banner ask it to allocate exabytes). Plain TCP
    only: ``tls://`` and other comms are left to the client's own timeout.
    """
    import socket
    import struct
    from urllib.parse import urlparse

    if not address.startswith("tcp://"):
        return
    timeout = float(config.get("connect-timeout") if timeout is None else timeout)
    url = urlparse(address)
    host, port = url.hostname, url.port
    if not host or port is None:
        raise InputError(f"scheduler {address!r}: expected tcp://host:port")
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            sock.settimeout(timeout)
            head = b""
            while len(head) < 8:
                part = sock.recv(8 - len(head))
                if not part:
                    break
                head += part
    except socket.timeout:
        raise InputError(f"scheduler {address}: something listens there but sent no Dask handshake within "
                         f"{timeout:g} s (an HTTP server or another service?)") from None
    except OSError as exc:
        raise InputError(f"cannot reach scheduler {address}: {exc.strerror or exc}") from None
    if len(head) < 8:
        raise InputError(f"scheduler {address}: the connection was closed without a Dask handshake")
    (nbytes,) = struct.unpack("<Q", head)
    if nbytes > 1 << 20:
        shown = head.decode("latin-1").encode("unicode_escape").decode()
        raise InputError(f"scheduler {address} is not a Dask scheduler (it answered {shown!r})")


def check_scheduler(scheduler) -> None:
    """Check a scheduler option before any output is written: its form, and for a TCP
    address that a Dask scheduler answers there (:func:`probe_scheduler`)."""
    if scheduler is None or scheduler == "threads" or not isinstance(scheduler, str):
        return
    if scheduler.startswith("local"):
        local_workers(scheduler)
        return
    if "://" not in scheduler:
        raise InputError(
            f"scheduler {scheduler!r}: expected 'threads', 'local[:N]' or an address like tcp://host:8786"
        )
    probe_scheduler(scheduler)


def _wait_for_workers(client, address: str) -> None:
    """A cluster without workers would wait for ever: wait a bounded time, then refuse."""
    if client.scheduler_info().get("workers"):
        return
    timeout = float(config.get("worker-timeout"))
    log.warning("scheduler %s has no workers yet: waiting up to %g s (chunkdic.worker-timeout)", address, timeout)
    try:
        client.wait_for_workers(1, timeout=timeout)
    except Exception:  # noqa: BLE001 - distributed raises its own TimeoutError subclasses
        raise InputError(f"scheduler {address} has no workers (waited {timeout:g} s, chunkdic.worker-timeout): "
                         "start workers or use another scheduler") from None


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
        client, cluster = start_local_cluster(local_workers(scheduler))
        runner = DistributedRunner(client, cluster)
    elif isinstance(scheduler, str):
        from distributed import Client

        check_scheduler(scheduler)
        timeout = float(config.get("connect-timeout"))
        try:
            client = Client(scheduler, timeout=f"{timeout}s")
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot reach scheduler {scheduler}: {exc}".splitlines()[0]) from None
        except (TypeError, ValueError) as exc:  # e.g. tls:// without certificates configured
            raise InputError(
                f"cannot connect to {scheduler} ({exc}); for tls:// set distributed.comm.tls.* "
                "(see docs/distributed.md)".splitlines()[0]
            ) from None
        try:
            _wait_for_workers(client, scheduler)
        except BaseException:
            client.close()
            raise
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




_LIBC: list = []


#: glibc's ``mallopt`` parameter of the mmap threshold
_M_MMAP_THRESHOLD = -3
#: buffers from this size up come from their own mappings once :func:`pin_mmap_threshold` ran (bytes)
MMAP_THRESHOLD = 1 << 20


def _libc():
    if not _LIBC:
        try:
            libc = ctypes.CDLL("libc.so.6")
            libc.malloc_trim.argtypes = [ctypes.c_size_t]
            libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        except (OSError, AttributeError):
            libc = None
        _LIBC.append(libc)
    return _LIBC[0]


def pin_mmap_threshold() -> None:
    """Give every buffer of :data:`MMAP_THRESHOLD` or more a mapping of its own, returned to the
    system when freed (glibc's ``M_MMAP_THRESHOLD``, which also stops the threshold's rise).

    For a process that holds a level's mesh data in node blocks (its client): its memory is
    then the mesh-sized arrays it holds, not the heaps that the freed ones of up to 32 MB (the
    threshold's rise) leave resident. ``bench_client_memory.py --mesh-data blocks
    --iterations 2`` at 768³ and 1024³, ℓ = 8: the client's peak 837 and 1 026 MiB with the
    rising threshold, 604 and 745 MiB with this one (docs/distributed.md). A no-op without glibc.
    """
    libc = _libc()
    if libc is not None:
        libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)


def release_freed_memory() -> None:
    """Return to the system the pages that freed buffers leave in glibc's heaps (``malloc_trim``).

    glibc raises its mmap threshold to the largest buffer freed (up to 32 MB), after which
    a task's NumPy arrays come from heaps whose freed pages stay resident: in the embedded
    pool, where the tasks' threads are the client's process, a 512³ run's peak grew to
    0.73 GiB over the level-0 passes, against 0.40 GiB with ``MALLOC_MMAP_THRESHOLD_=65536``
    in the environment. Called by the passes (:meth:`chunkdic.passes.level.LevelPasses._map`) at
    most every :data:`TRIM_SECONDS`, it brought the peak to 0.61-0.62 GiB (0.62 GiB every
    0.25 s); a no-op without glibc. (Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_`` for its
    workers itself.)
    """
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


def threads_of(scheduler) -> tuple[int, int, bool]:
    """``(tasks at once per process, tasks at once in all, tasks in other processes)`` for a
    ``scheduler`` argument (an address not yet reached counts as one worker per core here)."""
    cores = os.cpu_count() or 1
    if scheduler is None or scheduler == "threads":
        n = int(config.get("num-threads") or cores)
        return n, n, False
    if isinstance(scheduler, str) and scheduler.startswith("local"):
        # a LocalCluster of single-threaded workers (chunkdic.scheduler.open_runner)
        return 1, local_workers(scheduler) or cores, True
    info = getattr(scheduler, "scheduler_info", None)
    if callable(info):
        nthreads = [int(w.get("nthreads", 1)) for w in info().get("workers", {}).values()] or [1]
        return max(nthreads), sum(nthreads), True
    return 1, cores, True
