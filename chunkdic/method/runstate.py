"""What a correlation carries from level to level, and what its checkpoint holds.

One :class:`RunState` per run: the history of every pass, the status of each finished
level, the rigid translation and the two diagnostic gaps, and the Gauss–Newton state of
the level being solved. Its JSON form and arrays are exactly what a checkpoint stores
(:mod:`chunkdic.engine.checkpoint`), so a resumed run rebuilds it with
:meth:`RunState.from_checkpoint`. What the finest level leaves for the result (weak and
masked nodes, uncertainty, noise) is a :class:`~chunkdic.method.level_solve.LevelOutcome`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .stopping import History, State


@dataclasses.dataclass
class RunState:
    """A run's state across levels.

    Attributes
    ----------
    history : History
        Every pass of every level (rigid passes with negative iteration numbers).
    statuses : dict of int to str
        Status of each finished level.
    rigid_t : ndarray, shape (3,), float64, optional
        The start translation on the coarsest level, voxels of that level (rigid step, or
        the mean of an ``init`` field).
    initial_gap, rigid_gap : float, optional
        Gaps of the zero and rigid fields on the finest level (diagnostics, paper 5.1).
    gn : State, optional
        The Gauss–Newton state of the level being solved; ``None`` between levels.
    resumed_level : int, optional
        The level a resumed run was interrupted on (levels coarser than it are done).
    """

    history: History = dataclasses.field(default_factory=History)
    statuses: dict[int, str] = dataclasses.field(default_factory=dict)
    rigid_t: np.ndarray | None = None
    initial_gap: float | None = None
    rigid_gap: float | None = None
    gn: State | None = None
    resumed_level: int | None = None

    @classmethod
    def from_checkpoint(cls, saved: dict) -> "RunState":
        """The state saved by :meth:`to_json` and :meth:`arrays` (``saved["arrays"]``)."""
        return cls(history=History(saved["history"]),
                   statuses={int(k): v for k, v in saved["statuses"].items()},
                   rigid_t=np.array(saved["rigid_t"]),
                   initial_gap=saved.get("initial_gap"), rigid_gap=saved.get("rigid_gap"),
                   gn=State.restore(saved["gn"], saved["arrays"]), resumed_level=int(saved["level"]))

    def done_before_resume(self, s: int) -> bool:
        """Level ``s`` was finished before the interruption (levels run coarsest first)."""
        return self.resumed_level is not None and s > self.resumed_level

    def level_to_solve(self, s: int, finest: int) -> bool:
        """Whether level ``s`` is to be solved: a new level, one whose iterations were under way,
        or a resumed level whose iterations had ended but whose end is to be redone: the kill
        came before the end was recorded (``s`` not in ``statuses``: the regularisation length
        may still be to choose), or it is the finest level, whose solver gives the result's
        weak nodes, mask flags and uncertainty. A finished coarse level only hands its field on."""
        return self.gn is None or self.gn.status is None or s not in self.statuses or s == finest

    def to_json(self, s: int) -> dict:
        """The checkpoint's scalars while level ``s`` is solved."""
        return {"level": s, "gn": self.gn.scalars(), "statuses": {str(k): v for k, v in self.statuses.items()},
                "history": self.history.to_json(), "rigid_t": self.rigid_t.tolist(),
                "initial_gap": self.initial_gap, "rigid_gap": self.rigid_gap}

    def arrays(self) -> dict[str, np.ndarray]:
        """The checkpoint's arrays (the Gauss–Newton fields)."""
        return self.gn.arrays()
