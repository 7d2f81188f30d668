"""Typed events: every stage of a correlation reports a record that is worded by its own class
and reads as the mapping a script's callback expects."""

from __future__ import annotations

import numpy as np

import chunkdic
from chunkdic.method.events import STAGES, Event, EventText, Iteration, as_event


def test_every_event_of_a_run_is_a_worded_record_that_reads_as_a_mapping():
    rng = np.random.default_rng(0)
    f = rng.random((40, 40, 40)).astype(np.float32)
    events = []
    chunkdic.correlate(f, np.roll(f, 1, axis=0), element_size=16, coarsest=0, progress=events.append)
    stages = [e["stage"] for e in events]
    assert {"start", "plan", "matrix", "rigid", "affine", "start-choice", "gaps", "iteration", "level"} <= set(stages)
    text = EventText()
    for e in events:
        assert isinstance(e, Event) and type(e) is STAGES[e.stage]
        assert text(e)  # worded by its class, never the plain "stage: key=value" of the log's fallback
        assert as_event(dict(e)) == e  # the mapping holds the whole record
    last = [e for e in events if isinstance(e, Iteration)][-1]
    assert last.get("status") == last.status == "converged" and last["level"] == 0 and "seconds" in last


def test_a_mapping_of_a_known_stage_is_worded_as_its_record():
    line = EventText()({"stage": "level", "level": 0, "status": "converged", "gap": 0.01, "seconds": 2.0, "extra": 1})
    assert line == "level 0: converged, gap 1.000% (2.0 s)"
    assert EventText()({"stage": "element-size", "element_size": 8}) is None
