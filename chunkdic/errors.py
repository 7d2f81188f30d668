"""Errors that chunkdic raises for bad user input."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (missing file, wrong shape, ROI outside the volume, ...).

    The message is one line that tells the user what to change; the CLI prints it
    without a traceback and exits with status 2.
    """
