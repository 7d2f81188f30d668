"""What a result holds: its arrays with their dimensions and units, the history's columns, the node flags.

Shared by the result's group (:mod:`chunkdic.results.result`), the method that fills the
history (:class:`chunkdic.method.stopping.History`) and the run that flags the nodes
(:func:`chunkdic.results.result.node_flags`); it imports nothing.
"""

from __future__ import annotations

__all__ = ["HISTORY_FIELDS", "FLAG_NO_DATA", "FLAG_WEAK", "FLAG_MASKED", "LAYOUT", "HISTORY_LAYOUT"]

#: the columns of a result's history: one row per pass of every level
HISTORY_FIELDS = ("level", "iteration", "gap", "max_delta", "excluded")

#: node flag: the node's elements hold (almost) no voxel that maps inside ``g``; its
#: displacement is NaN (not measured)
FLAG_NO_DATA = 1
#: node flag: poorly textured (its 3x3 block of ``M`` is nearly singular); regularised,
#: its value is unreliable. Also set on the few nodes a level converged at the noise level
#: still moved by more than ``STEP_CAP`` × their uncertainty (docs/engine.md, "Iterations
#: and stopping"): poorly seen too, their value is not settled
FLAG_WEAK = 2
#: node flag: outside the specimen mask (no active element around it); NaN, not measured
FLAG_MASKED = 4

#: dimension names, unit and description of every array of a result group (the ``units``
#: follow CF usage: ``"1"`` is dimensionless; ``"voxel"`` is a voxel of the correlated level)
LAYOUT: dict[str, tuple[tuple[str, ...], str, str]] = {
    "displacement": (("component", "z", "y", "x"), "voxel", "nodal displacement, components (Uz, Uy, Ux)"),
    "node_coords": (("component", "z", "y", "x"), "voxel", "node position, components (z, y, x)"),
    "uncertainty": (("component", "z", "y", "x"), "voxel",
                    "standard uncertainty of the nodal displacement, components (z, y, x)"),
    "strain": (("component_i", "component_j", "ez", "ey", "ex"), "1",
               "small-strain tensor at the element centres, axes (z, y, x)"),
    "flags": (("z", "y", "x"), "1", "node flags (bits): 1 no data, 2 weak texture, 4 masked"),
    "active": (("ez", "ey", "ex"), "1", "element took part (specimen mask)"),
    "brightness": (("gain_offset", "ez", "ey", "ex"), "1",
                   "per-element gain (dimensionless) and offset (grey levels of the level): f = gain g + offset"),
    "z": (("z",), "voxel", "node position along z"),
    "y": (("y",), "voxel", "node position along y"),
    "x": (("x",), "voxel", "node position along x"),
    "ez": (("ez",), "voxel", "element centre along z"),
    "ey": (("ey",), "voxel", "element centre along y"),
    "ex": (("ex",), "voxel", "element centre along x"),
}
#: the same for the arrays of the ``history`` group (one entry per level and iteration)
HISTORY_LAYOUT: dict[str, tuple[tuple[str, ...], str, str]] = {
    "level": (("step",), "1", "pyramid level"),
    "iteration": (("step",), "1", "iteration (negative: rigid-translation steps)"),
    "gap": (("step",), "1", "matching gap rms(r) / (max f - min f) (paper 5.1)"),
    "max_delta": (("step",), "voxel", "max |da| of the update that followed (NaN: final evaluation)"),
    "excluded": (("step",), "voxel", "voxels left out (X + u(X) outside the deformed scan); a count"),
}
