"""Errors that chunkdic raises for bad user input."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (missing file, wrong shape, ROI outside the volume, ...).

    The message is one line that tells the user what to change; the CLI prints it
    without a traceback and exits with status 2.
    """


class WorkerLostError(RuntimeError):
    """The Dask cluster lost the workers a run needs and it cannot continue: the scheduler
    gave up on a task whose workers kept dying (``KilledWorker``), or no worker is left.

    Not bad input: the CLI says it in one line and exits with status 1. What the run saved
    stays (a correlation's checkpoint, a series' complete steps), so the same command
    resumes once the cluster is healthy.
    """


class DiskSpaceError(InputError):
    """The disk cannot hold what the run writes: refused up front by the plan, or a disk
    error (full, read-only, I/O) met while writing. ``kept``: the output was kept with a
    checkpoint the same command resumes from (the message says so); ``cause``: the disk
    error alone, without what follows from it."""

    def __init__(self, message: str, *, cause: str | None = None, kept: bool = False):
        super().__init__(message)
        self.cause = cause or message
        self.kept = kept
