"""Schedulers: what chunkdic starts by itself listens on loopback only."""

from __future__ import annotations

from urllib.parse import urlparse

from chunkdic.scheduler import ThreadRunner, open_runner


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
