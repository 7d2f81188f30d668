"""Engine events: one progress record per stage, logged and handed to the caller's callback.

An event is a flat dict (``stage`` plus its figures); the CLI prints them
(:func:`chunkdic.cli.common.print_progress`), a script passes its own ``progress``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

log = logging.getLogger(__name__)


def emit(progress: Callable[[dict], None] | None, **event) -> None:
    """Log an engine event and hand it to the caller's ``progress`` callback."""
    log.info("%s", event)
    if progress is not None:
        progress(event)
