"""Schedulers: what chunkdic starts by itself listens on loopback only."""

from __future__ import annotations

import gc
import time
import warnings
import weakref
from urllib.parse import urlparse

import numpy as np
import pytest

from chunkdic.scheduler import ThreadRunner, open_runner

# end-to-end runs (whole commands, clusters, kills): `pytest -m 'not slow'` leaves them out
pytestmark = pytest.mark.slow


def test_local_cluster_listens_on_loopback_only():
    with open_runner("local:2") as runner:
        client = runner.client
        info = client.scheduler_info()
        assert urlparse(client.scheduler.address).hostname == "127.0.0.1"
        assert len(info["workers"]) == 2
        for address in info["workers"]:
            assert urlparse(address).hostname == "127.0.0.1"
        assert urlparse(runner.dashboard_link).hostname == "127.0.0.1"
        # tasks run and come back through the streaming reduction
        assert sorted(runner.map_unordered(pow, [(2, k) for k in range(5)])) == [1, 2, 4, 8, 16]


def test_embedded_runner_is_the_default():
    with open_runner(None) as runner:
        assert isinstance(runner, ThreadRunner)
        assert sorted(runner.map_unordered(pow, [(3, k) for k in range(3)])) == [1, 3, 9]


def test_embedded_runner_forgets_each_result_once_handed_over():
    # a pass's partial results must not pile up until the pass ends (the M pass of a
    # level-0 2048^3 run returns 5.8 GB of them)
    with open_runner(None) as runner:
        seen = []
        for k, part in enumerate(runner.map_unordered(np.full, [(1000, i) for i in range(40)])):
            seen.append(weakref.ref(part))
            del part
            if k == 30:
                gc.collect()
                assert sum(r() is not None for r in seen) <= 1, "results of the pass are still held"


def test_embedded_runner_takes_its_arguments_as_it_submits_them():
    # the engine's passes hand a generator of arguments (each block's slice of the nodal
    # field made on demand): the pool takes a window ahead, not the whole pass at once
    from chunkdic.scheduler import WINDOW

    taken = []

    def args():
        for i in range(200):
            taken.append(i)
            yield (i, 2)

    with open_runner(None) as runner:
        results = runner.map_unordered(pow, args())
        first = next(results)
        assert len(taken) <= 2 * WINDOW * runner.n_workers, len(taken)  # the window and its refill
        assert sorted([first, *results]) == [i**2 for i in range(200)]


def test_scan_commands_run_on_a_local_cluster_with_progress(tmp_path, capsys):
    """synth, pyramid and ingest with --scheduler local:2: same voxels as the analytic
    texture / numpy sums / the source, and progress lines from the distributed futures."""
    import re

    import numpy as np

    from chunkdic.cli.app import main
    from chunkdic.io.scan import open_scan
    from chunkdic.synth import foam

    out = tmp_path / "pair"
    assert main(["synth", str(out), "--shape", "32", "--chunks", "8", "--dtype", "uint16", "--seed", "3",
                 "--field", "none", "--scheduler", "local:2"]) == 0
    err = capsys.readouterr().err
    assert "running on dask.distributed cluster" in err and "dashboard http://127.0.0.1:" in err
    percents = [int(p) for p in re.findall(r"synth:\s+(\d+)%", err)]
    # at most one progress line per 5 s since issue 23 (tests/cli/test_quiet.py checks the rate with a
    # fake clock): lines in order, then the summary of the finished step
    assert percents and percents == sorted(percents) and "synth: wrote" in err
    ref = out / "ref.zarr"
    level0 = open_scan(str(ref)).level(0).compute()
    np.testing.assert_array_equal(level0, foam.render((32, 32, 32), seed=3, dtype="uint16"))

    assert main(["pyramid", str(ref), "--levels", "2", "--scheduler", "local:2"]) == 0
    err = capsys.readouterr().err
    assert re.findall(r"pyramid:\s+\d+%", err)  # at least its 100 % line (one line per 5 s at most)
    sums = level0.astype(np.int64).reshape(8, 4, 8, 4, 8, 4).sum(axis=(1, 3, 5))
    np.testing.assert_array_equal(open_scan(str(ref)).level(2).compute(), sums)

    np.save(tmp_path / "v.npy", level0)
    assert main(["ingest", str(tmp_path / "v.npy"), str(tmp_path / "v.zarr"), "--chunks", "8",
                 "--scheduler", "local:2"]) == 0
    np.testing.assert_array_equal(open_scan(str(tmp_path / "v.zarr")).level(0).compute(), level0)


def _sum(a):
    return float(a.sum())


def test_a_given_client_runs_tasks_and_is_local_only_when_everything_is_on_loopback():
    from distributed import Client, LocalCluster

    from chunkdic.scheduler import _on_loopback

    assert _on_loopback("tcp://127.0.0.1:8786") and _on_loopback("tls://localhost:1")
    assert not _on_loopback("tcp://10.0.0.5:8786") and not _on_loopback("tcp://node12:8786")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster, Client(cluster) as client:
        with open_runner(client) as runner:
            assert runner.local
            # tasks carrying 12.6 MB of nodal slices in all (a pass at 128³ nodes sends
            # ~70 MB) must not make distributed warn about a large graph on every pass
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                got = sorted(runner.map_unordered(_sum, [(np.full(65536, i, float),) for i in range(24)]))
            assert got == [65536.0 * i for i in range(24)]
            # each result is released on the workers once received, not at the end of the pass
            # (Future.release reaches the client's event loop asynchronously: allow it 10 s)
            results = runner.map_unordered(np.full, [(1000, i) for i in range(24)])
            try:
                for _ in range(20):
                    next(results)
                deadline = time.monotonic() + 10.0
                while len(client.futures) > 4 and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert len(client.futures) <= 4, len(client.futures)
            finally:
                results.close()


def test_numpy_inputs_on_a_two_worker_local_cluster_send_no_voxels_in_any_graph(tmp_path):
    """128³ float32 NumPy scans (8 MiB each) correlated on a 2-worker LocalCluster: with
    distributed's large-graph threshold lowered to 2 MiB and its warning made an error, no
    graph may carry a scan; the field is the known translation (exact Fourier shift)."""
    import dask
    from textures import smooth_noise

    import chunkdic

    n, t = 128, np.array([0.4, -0.3, 0.25])
    f = smooth_noise((n, n, n), sigma=2.0, seed=5)
    k = np.meshgrid(*[np.fft.fftfreq(n) for _ in range(3)], indexing="ij", sparse=True)
    g = np.fft.ifftn(np.fft.fftn(f) * np.exp(-2j * np.pi * sum(ki * ti for ki, ti in zip(k, t)))).real
    f, g = (1000 + 300 * f / f.std()).astype(np.float32), (1000 + 300 * g / f.std()).astype(np.float32)
    with dask.config.set({"distributed.admin.large-graph-warning-threshold": "2MiB"}), warnings.catch_warnings():
        warnings.filterwarnings("error", message="Sending large graph")
        res = chunkdic.correlate(f, g, element_size=16, scheduler="local:2", regularization="none")
    u = res.displacement.reshape(3, -1)
    assert res.converged
    np.testing.assert_allclose(np.median(u, axis=1), t, atol=0.01)


def test_a_closing_worker_drops_only_its_failed_heartbeat():
    """A worker that cancels its own heartbeat as it closes logs a traceback at ERROR that says
    nothing to act on; the same failure while the worker runs, and any other error, are kept."""
    import logging
    from types import SimpleNamespace

    from distributed.core import Status

    from chunkdic.worker_setup import _ClosingHeartbeat

    def shown(status, message):
        record = logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, message, None, None)
        return _ClosingHeartbeat(SimpleNamespace(status=status)).filter(record)

    heartbeat = "Failed to communicate with scheduler during heartbeat."
    for status in (Status.closing, Status.closing_gracefully, Status.closed):
        assert not shown(status, heartbeat)
        assert shown(status, "Unexpected exception during heartbeat. Closing worker.")
    assert shown(Status.running, heartbeat) and shown(Status.paused, heartbeat)


def _worker_filters():
    import logging

    return [type(f).__name__ for f in logging.getLogger("distributed.worker").filters]


def test_every_worker_of_the_local_cluster_drops_its_closing_heartbeat_and_keeps_the_users_preloads():
    import dask.config

    with dask.config.set({"distributed.worker.preload": ["json"]}), open_runner("local:1") as runner:
        client = runner.client
        spec = next(iter(runner._cluster.worker_spec.values()))
        assert spec["options"]["preload"] == ["json", "chunkdic.worker_setup"]
        assert list(client.run(_worker_filters).values()) == [["_ClosingHeartbeat"]]
        # the workers a nanny starts in place of others set up alike
        client.restart()
        assert list(client.run(_worker_filters).values()) == [["_ClosingHeartbeat"]]
