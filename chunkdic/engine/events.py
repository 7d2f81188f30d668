"""Engine events: one progress record per stage, logged as a line of text and handed to the caller's callback.

An event is a flat dict (``stage`` plus its figures). :class:`EventText` words it: the
engine's ``logging`` records (INFO, logger ``chunkdic.engine.events``) and the CLI's
progress lines (:func:`chunkdic.cli.common.print_progress`, which also explains each term
once per run) say the same thing; a script passes its own ``progress`` for the dicts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

from .stopping import STALL_PATIENCE, STEP_CAP

log = logging.getLogger(__name__)

#: one-line explanations of terms that appear in progress lines and summaries
EXPLAIN = {
    "stalled": "stalled: neither the gap nor the increments improved for {patience} passes; the best field "
               "so far is kept and not called converged (try a larger --element-size or regularisation)",
    "excluded": "excluded: voxels whose X + u(X) falls outside the deformed scan; they are left out of the "
                "sums (a large share means the ROI reaches past what the deformed scan shows)",
    "diverged": "diverged: the gap grew far above its best; the best field so far is kept, not converged",
    "max-iterations": "max-iterations: --max-iterations reached before max|da| fell under --tolerance",
    "rigid-rise": "the gap rose: the previous rigid step overshot; this uniform translation is only the "
                  "starting estimate, which the C8 iterations refine",
    "rigid-worse": "a single mean translation fits this field worse than no motion (strain or rotation "
                   "dominate); it is only a starting estimate, which the C8 iterations refine",
}


class EventText:
    """The line of text of an engine event (``None`` for a stage it does not word).

    With ``explain=True`` (the CLI), a term that needs it (``stalled``, ``excluded``, a rigid
    step that raised the gap, ...) is explained on a line of its own the first time in a run
    (:meth:`reset` starts a run); without (the log), every line is one line and the object
    keeps no state.
    """

    def __init__(self, explain: bool = False):
        self.explains = explain
        self.explained: set[str] = set()
        self.rigid_gap: dict = {}  # last rigid gap per level: a rigid step that raises it is explained

    def reset(self) -> None:
        self.explained.clear()
        self.rigid_gap.clear()

    def explain(self, term: str) -> str:
        """The explanation of ``term`` on a line of its own, the first time in this run."""
        if not self.explains or term not in EXPLAIN or term in self.explained:
            return ""
        self.explained.add(term)

        return "\n  (" + EXPLAIN[term].format(patience=STALL_PATIENCE) + ")"

    def __call__(self, event: dict) -> str | None:
        stage = event["stage"]
        explain = self.explain
        if stage == "start":
            roi = ",".join(f"{a}:{b}" for a, b in event["roi"])
            nodes = "x".join(str(n) for n in event["nodes"])
            line = f"running on {event['scheduler']}; levels {event['levels']}; ROI {roi} (level voxels); {nodes} nodes"
            if event.get("requested_roi"):
                asked = ",".join(f"{a}:{b}" for a, b in event["requested_roi"])
                line += f" (requested {asked} in level-0 voxels, trimmed to whole elements)"
            return line
        if stage == "plan":
            return event["plan"].line()
        if stage == "compile":
            if not event["done"]:
                return ("compiling the numba kernels (first run on this machine, about 20 s; "
                        "later runs load them from the cache)")
            return f"kernels compiled in {event['seconds']:.1f} s"
        if stage == "matrix":
            rate = event["voxels"] / max(event["seconds"], 1e-9) / 1e6
            if event.get("reused"):
                f = "; its low-passed f blocks reused" if event.get("f_adopted") else ""
                return (f"level {event['level']}: M read from the checkpoint of the interrupted run{f} "
                        f"({event['seconds']:.1f} s)")
            return (f"level {event['level']}: M built over {event['blocks']} blocks in {event['seconds']:.1f} s "
                    f"({rate:.1f} Mvoxel/s)")
        if stage == "f-copy":
            return (f"level {event['level']}: f low-passed again over {event['blocks']} blocks in "
                    f"{event['seconds']:.1f} s (M was read from the checkpoint)")
        if stage == "prepared":
            return (f"level {event['level']}: g prepared over {event['voxels'] / 1e6:.1f} Mvoxel in "
                    f"{event['seconds']:.1f} s")
        if stage == "rigid":
            t = ", ".join(f"{v:+.3f}" for v in event["translation"])
            rose = ""
            if self.explains:
                before = self.rigid_gap.get(event["level"]) if event["iteration"] else None
                self.rigid_gap[event["level"]] = event["gap"]
                rose = explain("rigid-rise") if before is not None and event["gap"] > before else ""
            return (f"level {event['level']} rigid {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  "
                    f"max|da| {event['max_delta']:.2e}  t=({t})" + rose)
        if stage == "affine":
            g = event["gradient"]
            return (f"level {event['level']} affine {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  "
                    f"max|da| {event['max_delta']:.2e}  dU/dX diagonal ({g[0][0]:+.4f}, {g[1][1]:+.4f}, "
                    f"{g[2][2]:+.4f})")
        if stage == "texture":
            return (f"level {event['level']}: texture autocorrelation length {event['length']:.1f} voxels; "
                    f"regularisation length {event['start_length']:.1f} voxels until the choice "
                    f"(elements of {event['element_size']})")
        if stage == "start-choice":
            names = {"rigid": "rigid + affine", "zero": "no motion", "init": "earlier field",
                     "translation": "translation alone"}
            gaps = ", ".join(f"{names.get(k, k)} {100 * v:.3f}%" for k, v in event["gaps"].items())
            return f"level {event['level']}: start {names.get(event['chosen'], event['chosen'])} (lowest gap of {gaps})"
        if stage == "gaps":
            worse = explain("rigid-worse") if event["rigid_gap"] > event["initial_gap"] else ""
            return (f"level {event['level']}: initial gap {100 * event['initial_gap']:.3f}%, after rigid translation "
                    f"{100 * event['rigid_gap']:.3f}%" + worse)
        if stage == "iteration":
            d = event.get("status", "final") if event["max_delta"] is None else f"{event['max_delta']:.2e}"
            notes = (explain("excluded") if event["excluded"] else "") + explain(event.get("status") or "")
            return (
                f"level {event['level']} iter {event['iteration']:2d}: gap {100 * event['gap']:.3f}%  max|da| {d}"
                f"  excluded {event['excluded']}  ({event['seconds']:.1f} s)" + notes
            )
        if stage == "blocks":
            return (f"  level {event['level']} {event['label']}: {event['done']}/{event['total']} blocks, "
                    f"{event['rate'] / 1e6:.1f} Mvoxel/s, ETA {event['eta']:.0f} s")
        if stage == "regularization":
            corner = event.get("l_curve_length")
            corner = f"; L-curve corner {corner:.1f}" if corner is not None and math.isfinite(corner) else ""
            return (f"level {event['level']}: {event['kind']} regularisation length {event['length']:.1f} voxels "
                    f"(chosen from the data{corner}; noise correlation factor {event['kappa']:.1f})")
        if stage == "reweighting":
            if not event["freed"]:
                return (f"level {event['level']}: robust reweighting {event['round']}: no curvature term beyond "
                        f"the threshold, length {event['length']:.1f} voxels kept")
            return (f"level {event['level']}: robust reweighting {event['round']}: {event['freed']} curvature terms "
                    f"({100 * event['fraction']:.2f}%) left free, length chosen again {event['length']:.1f} voxels")
        if stage == "init":
            mean = ", ".join(f"{v:+.3f}" for v in event["mean"])
            return (f"level {event['level']}: starting from the field of {event['path']} "
                    f"(mean {mean} voxels of the level)")
        if stage == "series-step":
            what = {"computed": "correlating", "resumed": "resuming",
                    "done before": "done before, skipped:"}[event["run"]]
            return f"series: {what} {event['group']} (scans {event['pair']})"
        if stage == "complete":
            return f"{event['path']} is already complete (the same inputs and settings): nothing to do"
        if stage == "resume":
            reused = {("M", "scans"): "; reusing M and the prepared scans of the interrupted run",
                      ("M",): "; reusing M (the interrupted run's prepared scans are gone: prepared again)",
                      ("scans",): "; reusing the prepared scans of the interrupted run"}
            return (f"resuming the interrupted run from its checkpoint: level {event['level']}, "
                    f"iteration {event['iteration']}" + reused.get(tuple(event.get("reused", ())), ""))
        if stage == "scratch-kept":
            return (f"the prepared scans ({event['bytes'] / 2**30:.2f} GiB in {event['path']}) are kept for the "
                    f"resume: run the same command again; to give up, remove {event['output']} (the next chunkdic "
                    "run then removes them)")
        if stage == "unsettled":
            return (f"level {event['level']}: converged at the noise level; {event['nodes']} poorly seen nodes still "
                    f"moved by more than {STEP_CAP:g}x their uncertainty and are flagged weak (unreliable)")
        if stage == "level":
            return (f"level {event['level']}: {event['status']}, gap {100 * event['gap']:.3f}% "
                    f"({event['seconds']:.1f} s)" + explain(event["status"]))
        return None


_LOG_TEXT = EventText()


def describe(event: dict) -> str:
    """One line for the log: :class:`EventText`'s wording, else ``stage: key=value, ...``."""
    try:
        line = _LOG_TEXT(event)
    except (KeyError, TypeError, ValueError):  # an event of another shape: its fields, plainly
        line = None
    if line is None:
        rest = ", ".join(f"{k}={v}" for k, v in event.items() if k != "stage")
        line = f"{event.get('stage')}: {rest}"
    return line.strip()


def emit(progress: Callable[[dict], None] | None, **event) -> None:
    """Log an engine event (a worded line, INFO) and hand the dict to the caller's ``progress`` callback."""
    if log.isEnabledFor(logging.INFO):
        log.info("%s", describe(event))
    if progress is not None:
        progress(event)
