"""The events of a correlation: one typed record per stage, worded here and nowhere else.

Every stage of a run reports one frozen dataclass (:class:`Iteration`, :class:`Matrix`,
:class:`Rigid`, ...) through :func:`emit`, which logs its line (INFO, logger
``chunkdic.method.events``) and hands the record to the caller's ``progress`` callback.
Each record is also a read-only mapping (``event["stage"]``, ``event.get("level")``,
``dict(event)``), so a script's callback reads it as a dict. Each class words itself
(:meth:`Event.words`); :class:`EventText` adds the explanations a person at a terminal
needs once per run (the CLI's progress lines, :func:`chunkdic.cli.common.print_progress`).
The method emits the Gauss–Newton and start stages, the passes theirs, the run the rest;
the studies (series, uncertainty, sweep, resolution, repeats, cut check) emit the records of
:mod:`chunkdic.analysis.study_events`, subclasses of :class:`Event` worded the same way.
Every subclass with a ``stage`` registers itself in :data:`STAGES` when its module is imported.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

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


#: the record class of every stage, filled as the classes are defined (:meth:`Event.__init_subclass__`)
STAGES: dict[str, type["Event"]] = {}


@dataclasses.dataclass(frozen=True, kw_only=True)
class Event(Mapping):
    """A stage's record; ``group``: the step of a loading series it belongs to (None: a lone run)."""

    stage: ClassVar[str] = ""
    #: the level at which :func:`emit` logs it (a frequent record, such as a share of a long step, logs lower)
    log_level: ClassVar[int] = logging.INFO
    group: str | None = None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("stage"):
            STAGES[cls.stage] = cls

    def __getitem__(self, key: str) -> Any:
        if key == "stage":
            return self.stage
        if key in self._names():
            return getattr(self, key)
        raise KeyError(key)

    def __iter__(self):
        yield "stage"
        yield from self._names()

    def __len__(self) -> int:
        return 1 + len(self._names())

    @classmethod
    def _names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    def words(self, text: "EventText") -> str | None:
        """The line of text of this event (``text`` explains terms once per run), or None."""
        return None


@dataclasses.dataclass(frozen=True, kw_only=True)
class Start(Event):
    stage: ClassVar[str] = "start"
    scheduler: str
    dashboard: str | None = None
    levels: list
    roi: list
    requested_roi: list | None = None
    nodes: list

    def words(self, text):
        roi = ",".join(f"{a}:{b}" for a, b in self.roi)
        nodes = "x".join(str(n) for n in self.nodes)
        line = f"running on {self.scheduler}; levels {self.levels}; ROI {roi} (level voxels); {nodes} nodes"
        if self.requested_roi:
            asked = ",".join(f"{a}:{b}" for a, b in self.requested_roi)
            line += f" (requested {asked} in level-0 voxels, trimmed to whole elements)"
        return line


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlanMade(Event):
    """The plan of the run (:class:`chunkdic.engine.runplan.Plan`), calibrated on the data."""

    stage: ClassVar[str] = "plan"
    plan: Any

    def words(self, text):
        return self.plan.line()


@dataclasses.dataclass(frozen=True, kw_only=True)
class Compile(Event):
    stage: ClassVar[str] = "compile"
    done: bool
    seconds: float | None = None

    def words(self, text):
        if not self.done:
            return "compiling the numba kernels (first run on this machine, about 20 s; later runs load them from the cache)"
        return f"kernels compiled in {self.seconds:.1f} s"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Matrix(Event):
    stage: ClassVar[str] = "matrix"
    level: int
    nodes: list
    blocks: int
    voxels: int
    seconds: float
    cpu_seconds: float = 0.0
    reused: bool = False
    f_adopted: bool = False

    def words(self, text):
        if self.reused:
            f = "; its low-passed f blocks reused" if self.f_adopted else ""
            return f"level {self.level}: M read from the checkpoint of the interrupted run{f} ({self.seconds:.1f} s)"
        rate = self.voxels / max(self.seconds, 1e-9) / 1e6
        return (f"level {self.level}: M built over {self.blocks} blocks in {self.seconds:.1f} s "
                f"({rate:.1f} Mvoxel/s)")


@dataclasses.dataclass(frozen=True, kw_only=True)
class FCopy(Event):
    stage: ClassVar[str] = "f-copy"
    level: int
    blocks: int
    seconds: float

    def words(self, text):
        return (f"level {self.level}: f low-passed again over {self.blocks} blocks in {self.seconds:.1f} s "
                "(M was read from the checkpoint)")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Prepared(Event):
    stage: ClassVar[str] = "prepared"
    level: int
    box: list
    voxels: int
    seconds: float

    def words(self, text):
        return f"level {self.level}: g prepared over {self.voxels / 1e6:.1f} Mvoxel in {self.seconds:.1f} s"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Blocks(Event):
    """A long pass's progress: blocks done, voxel rate, time still to go."""

    stage: ClassVar[str] = "blocks"
    level: int
    label: str
    done: int
    total: int
    rate: float
    eta: float

    def words(self, text):
        return (f"  level {self.level} {self.label}: {self.done}/{self.total} blocks, "
                f"{self.rate / 1e6:.1f} Mvoxel/s, ETA {self.eta:.0f} s")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Rigid(Event):
    stage: ClassVar[str] = "rigid"
    level: int
    iteration: int
    gap: float
    max_delta: float
    translation: list

    def words(self, text):
        t = ", ".join(f"{v:+.3f}" for v in self.translation)
        rose = text.rigid_rose(self.level, self.iteration, self.gap)
        return (f"level {self.level} rigid {self.iteration:2d}: gap {100 * self.gap:.3f}%  "
                f"max|da| {self.max_delta:.2e}  t=({t})" + rose)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Affine(Event):
    stage: ClassVar[str] = "affine"
    level: int
    iteration: int
    gap: float
    max_delta: float
    gradient: list

    def words(self, text):
        g = self.gradient
        return (f"level {self.level} affine {self.iteration:2d}: gap {100 * self.gap:.3f}%  "
                f"max|da| {self.max_delta:.2e}  dU/dX diagonal ({g[0][0]:+.4f}, {g[1][1]:+.4f}, {g[2][2]:+.4f})")


@dataclasses.dataclass(frozen=True, kw_only=True)
class StartChoice(Event):
    stage: ClassVar[str] = "start-choice"
    level: int
    chosen: str
    gaps: dict

    NAMES: ClassVar[dict] = {"rigid": "rigid + affine", "zero": "no motion", "init": "earlier field",
                             "translation": "translation alone"}

    def words(self, text):
        names = self.NAMES
        gaps = ", ".join(f"{names.get(k, k)} {100 * v:.3f}%" for k, v in self.gaps.items())
        return f"level {self.level}: start {names.get(self.chosen, self.chosen)} (lowest gap of {gaps})"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Gaps(Event):
    stage: ClassVar[str] = "gaps"
    level: int
    initial_gap: float
    rigid_gap: float
    translation: list
    seconds: float = 0.0
    cpu_seconds: float = 0.0

    def words(self, text):
        worse = text.explain("rigid-worse") if self.rigid_gap > self.initial_gap else ""
        return (f"level {self.level}: initial gap {100 * self.initial_gap:.3f}%, after rigid translation "
                f"{100 * self.rigid_gap:.3f}%" + worse)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Iteration(Event):
    """One Gauss–Newton pass (:func:`chunkdic.method.gauss_newton.iterate`); ``max_delta`` None:
    the level ended at this pass (``status``) without an increment."""

    stage: ClassVar[str] = "iteration"
    level: int
    iteration: int
    gap: float
    max_delta: float | None = None
    excluded: int = 0
    gain: float = 1.0
    status: str | None = None
    seconds: float = 0.0
    noise_step: float | None = None
    unsettled: int = 0
    assemble_seconds: float | None = None
    solve_seconds: float | None = None
    cg_iterations: int | None = None
    voxels: int | None = None
    assemble_cpu_seconds: float | None = None

    def words(self, text):
        d = (self.status or "final") if self.max_delta is None else f"{self.max_delta:.2e}"
        notes = (text.explain("excluded") if self.excluded else "") + text.explain(self.status or "")
        return (f"level {self.level} iter {self.iteration:2d}: gap {100 * self.gap:.3f}%  max|da| {d}"
                f"  excluded {self.excluded}  ({self.seconds:.1f} s)" + notes)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Texture(Event):
    """The reference's texture on the correlated level, read before the levels run
    (:mod:`chunkdic.engine.texture_check`): its autocorrelation length and the regularisation
    length a large deformation starts with on it (:func:`chunkdic.method.length.start_length`) and
    the one a fine texture starts with (``usual_length``), voxels of the level; emitted only when
    they differ (a coarse texture)."""

    stage: ClassVar[str] = "texture"
    level: int
    length: float
    start_length: float
    usual_length: float
    element_size: float
    smallest: int | None = None

    def words(self, text):
        return (f"level {self.level}: texture autocorrelation length {self.length:.1f} voxels; under a large "
                f"deformation the levels start with a regularisation length of {self.start_length:.1f} voxels "
                f"(elements of {self.element_size:g})")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Regularization(Event):
    stage: ClassVar[str] = "regularization"
    level: int
    length: float
    l_curve_length: float | None = None
    kind: str
    kappa: float
    rule: str
    seconds: float = 0.0

    def words(self, text):
        corner = self.l_curve_length
        corner = f"; L-curve corner {corner:.1f}" if corner is not None and math.isfinite(corner) else ""
        return (f"level {self.level}: {self.kind} regularisation length {self.length:.1f} voxels "
                f"(chosen from the data{corner}; noise correlation factor {self.kappa:.1f})")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Reweighting(Event):
    stage: ClassVar[str] = "reweighting"
    level: int
    round: int
    freed: int
    length: float
    fraction: float = 0.0
    seconds: float = 0.0

    def words(self, text):
        if not self.freed:
            return (f"level {self.level}: robust reweighting {self.round}: no curvature term beyond "
                    f"the threshold, length {self.length:.1f} voxels kept")
        return (f"level {self.level}: robust reweighting {self.round}: {self.freed} curvature terms "
                f"({100 * self.fraction:.2f}%) left free, length chosen again {self.length:.1f} voxels")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Init(Event):
    stage: ClassVar[str] = "init"
    level: int
    path: str | None
    mean: list

    def words(self, text):
        mean = ", ".join(f"{v:+.3f}" for v in self.mean)
        return f"level {self.level}: starting from the field of {self.path} (mean {mean} voxels of the level)"


@dataclasses.dataclass(frozen=True, kw_only=True)
class Unsettled(Event):
    stage: ClassVar[str] = "unsettled"
    level: int
    nodes: int

    def words(self, text):
        return (f"level {self.level}: converged at the noise level; {self.nodes} poorly seen nodes still "
                f"moved by more than {STEP_CAP:g}x their uncertainty and are flagged weak (unreliable)")


@dataclasses.dataclass(frozen=True, kw_only=True)
class LevelDone(Event):
    stage: ClassVar[str] = "level"
    level: int
    status: str
    gap: float
    seconds: float

    def words(self, text):
        return (f"level {self.level}: {self.status}, gap {100 * self.gap:.3f}% ({self.seconds:.1f} s)"
                + text.explain(self.status))


@dataclasses.dataclass(frozen=True, kw_only=True)
class Resume(Event):
    stage: ClassVar[str] = "resume"
    level: int
    iteration: int
    reused: list = dataclasses.field(default_factory=list)

    WORDS: ClassVar[dict] = {("M", "scans"): "; reusing M and the prepared scans of the interrupted run",
                             ("M",): "; reusing M (the interrupted run's prepared scans are gone: prepared again)",
                             ("scans",): "; reusing the prepared scans of the interrupted run"}

    def words(self, text):
        return (f"resuming the interrupted run from its checkpoint: level {self.level}, iteration {self.iteration}"
                + self.WORDS.get(tuple(self.reused), ""))


@dataclasses.dataclass(frozen=True, kw_only=True)
class ScratchKept(Event):
    stage: ClassVar[str] = "scratch-kept"
    path: str
    bytes: int
    output: str

    def words(self, text):
        return (f"the prepared scans ({self.bytes / 2**30:.2f} GiB in {self.path}) are kept for the resume: run "
                f"the same command again; to give up, remove {self.output} (the next chunkdic run then removes them)")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Complete(Event):
    stage: ClassVar[str] = "complete"
    path: str

    def words(self, text):
        return f"{self.path} is already complete (the same inputs and settings): nothing to do"


def as_event(event: Mapping) -> Event | None:
    """``event`` as its stage's record (a plain mapping with a known ``stage`` converted,
    its unknown keys left out), or None for a stage no imported module declares."""
    if isinstance(event, Event):
        return event
    cls = STAGES.get(event.get("stage"))
    if cls is None:
        return None
    return cls(**{k: v for k, v in event.items() if k in cls._names()})


class EventText:
    """The line of text of an event (``None`` for a stage it does not word).

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

    def rigid_rose(self, level: int, iteration: int, gap: float) -> str:
        """The explanation of a rigid step that raised the gap of the one before it, once."""
        if not self.explains:
            return ""
        before = self.rigid_gap.get(level) if iteration else None
        self.rigid_gap[level] = gap
        return self.explain("rigid-rise") if before is not None and gap > before else ""

    def __call__(self, event: Mapping) -> str | None:
        record = as_event(event)
        return None if record is None else record.words(self)


_LOG_TEXT = EventText()


def describe(event: Mapping) -> str:
    """One line for the log: the event's own wording, else ``stage: key=value, ...``."""
    try:
        line = _LOG_TEXT(event)
    except (KeyError, TypeError, ValueError):  # a record of another shape: its fields, plainly
        line = None
    if line is None:
        rest = ", ".join(f"{k}={v}" for k, v in event.items() if k != "stage")
        line = f"{event.get('stage')}: {rest}"
    return line.strip()


def emit(progress: Callable[[Event], None] | None, event: Event) -> None:
    """Log an event (its line, INFO) and hand the record to the caller's ``progress`` callback."""
    if log.isEnabledFor(event.log_level):
        log.log(event.log_level, "%s", describe(event))
    if progress is not None:
        progress(event)
