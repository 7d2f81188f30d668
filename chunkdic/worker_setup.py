"""Set-up of the worker processes of chunkdic's own LocalCluster (a Dask preload module).

``distributed`` runs :func:`dask_setup` in every worker process it starts, including the one
a nanny starts in place of a worker that died. A worker closing while its heartbeat is in
flight logs the heartbeat's failure, with a traceback, at ERROR: the worker cancels its own
connection to the scheduler. That happens when a run ends, most often on a loaded machine and
after a worker was replaced; the run is complete and the traceback says nothing a user can act
on. :func:`dask_setup` drops that one message from a worker that is closing; a heartbeat that
fails while the worker runs is still logged.
"""

from __future__ import annotations

import logging

from distributed.core import Status

#: how ``distributed.worker`` starts the message of a failed heartbeat
HEARTBEAT_FAILED = "Failed to communicate with scheduler during heartbeat"


class _ClosingHeartbeat(logging.Filter):
    """Refuses the failed-heartbeat record of a worker that is closing or closed."""

    def __init__(self, worker):
        super().__init__()
        self.worker = worker

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.getMessage().startswith(HEARTBEAT_FAILED)
                    and self.worker.status in (Status.closing, Status.closing_gracefully, Status.closed))


def dask_setup(worker) -> None:
    """Called by ``distributed`` in each worker process at its start (``preload``)."""
    logging.getLogger("distributed.worker").addFilter(_ClosingHeartbeat(worker))
