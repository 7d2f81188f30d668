"""A correlation result and its Zarr v3 group.

The group holds small arrays only (mesh-sized): ``displacement`` and ``node_coords``
``(3, nz, ny, nx)`` float64 in voxels of the correlated level, and the iteration history
``history/level``, ``history/iteration``, ``history/gap``, ``history/max_delta``,
``history/excluded``, and the element strains ``strain`` ``(3, 3, ez, ey, ex)`` float64
(dimensionless, :mod:`chunkdic.strain`; computed from ``displacement`` when the result
is saved, absent from results written before it existed). Everything else is in ``attrs["chunkdic"]``. The group is created
with ``complete: false`` and marked complete last, so an interrupted write is never
mistaken for a result.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .mesh import Mesh

HISTORY_FIELDS = ("level", "iteration", "gap", "max_delta", "excluded")

#: node flag: the node's elements hold (almost) no voxel that maps inside ``g``; its
#: displacement is NaN (not measured)
FLAG_NO_DATA = 1
#: node flag: poorly textured (its 3x3 block of ``M`` is nearly singular); regularised,
#: its value is unreliable
FLAG_WEAK = 2
#: node flag: outside the specimen mask (no active element around it); NaN, not measured
FLAG_MASKED = 4


@dataclass
class Result:
    """Outcome of :func:`chunkdic.correlate`.

    Attributes
    ----------
    displacement : ndarray, shape (3, nz, ny, nx), float64, voxels of ``level``
        Nodal displacement, components ``(z, y, x)`` (``Uz, Uy, Ux``).
    node_coords : ndarray, shape (3, nz, ny, nx), float64, voxels of ``level``
        Node positions.
    history : dict of 1-D ndarrays
        Per level and iteration: ``level``, ``iteration``, matching gap ``gap``
        (paper section 5.1), ``max_delta`` = max |δa| of the update that followed
        (NaN for the final evaluation), ``excluded`` voxels.
    info : dict
        Everything else: ``element_size``, ``roi`` (level voxels, ``[[z0, z1], …]``),
        ``roi_level0``, ``level``, ``scale`` (voxel edge in level-0 voxels),
        ``voxel_size``, ``unit``, ``converged``, ``status``, ``initial_gap``,
        ``rigid_gap``, ``final_gap``, ``rigid_translation``, ``excluded_voxels``,
        ``used_voxels``, settings and inputs.
    strain : ndarray, shape (3, 3, ez, ey, ex), float64, optional
        Small-strain tensor per element at the element centres (paper section 5.4), axes
        ``(z, y, x)``; ``None`` until computed (:meth:`element_strain` computes it).
    flags : ndarray, shape (nz, ny, nx), uint8, optional
        Per-node flags, bits :data:`FLAG_NO_DATA` (displacement NaN: not measured),
        :data:`FLAG_WEAK` (poorly textured, regularised) and :data:`FLAG_MASKED` (outside
        the specimen mask, NaN).
    active : ndarray, shape (ez, ey, ex), uint8, optional
        Elements that took part (a specimen mask's material elements, :mod:`chunkdic.masks`);
        ``None`` without a mask.
    uncertainty : ndarray, shape (3, nz, ny, nx), float64, optional
        Standard deviation of each nodal displacement from the final residual's noise,
        voxels of ``level`` (:func:`chunkdic.noise.nodal_uncertainty`); NaN where not measured.
    brightness : ndarray, shape (2, ez, ey, ex), float64, optional
        Per-element gain and offset of the grey-level model (:mod:`chunkdic.greylevel`):
        ``f(X) ≈ gain · g(X + u(X)) + offset``, grey levels of the correlated level.
    """

    displacement: np.ndarray
    node_coords: np.ndarray
    history: dict[str, np.ndarray]
    info: dict = field(default_factory=dict)
    path: str | None = None
    strain: np.ndarray | None = None
    flags: np.ndarray | None = None
    brightness: np.ndarray | None = None
    active: np.ndarray | None = None
    uncertainty: np.ndarray | None = None

    @property
    def converged(self) -> bool:
        return bool(self.info.get("converged", False))

    @property
    def final_gap(self) -> float:
        return float(self.info["final_gap"])

    @property
    def mesh(self) -> Mesh:
        roi = self.info["roi"]
        ell = int(self.info["element_size"])
        return Mesh(tuple(int(a) for a, _ in roi), ell, tuple((b - a) // ell for a, b in roi))

    def element_strain(self) -> np.ndarray:
        """Element strains ``(3, 3, ez, ey, ex)`` (stored, else computed and kept)."""
        if self.strain is None:
            from .strain import element_strain

            self.strain = element_strain(self.displacement, self.info["element_size"])
        return self.strain

    def __repr__(self) -> str:
        i = self.info
        return (
            f"<chunkdic.Result {self.displacement.shape[1:]} nodes, ell={i.get('element_size')} "
            f"level={i.get('level')} status={i.get('status')} final_gap={i.get('final_gap', float('nan')):.4g}>"
        )

    def save(self, path: str | os.PathLike, *, overwrite: bool = False, inputs=()) -> None:
        """Write the result as a Zarr v3 group (complete flag set last).

        The group is written next to ``path`` and renamed into place when complete, so an
        existing result is replaced only by a complete one. ``overwrite`` replaces only a
        result that chunkdic wrote (:mod:`chunkdic.outputs`); ``inputs`` (paths) may not
        be, contain or hold ``path``.
        """
        import zarr

        from .outputs import Outputs

        plan = Outputs(inputs=inputs, overwrite=overwrite)
        entry = plan.add(path, "result")
        with plan:
            root = zarr.open_group(str(entry.work), mode="w", zarr_format=3)
            root.attrs["chunkdic"] = {**_jsonable(self.info), "kind": "result", "complete": False}
            for name, arr in (("displacement", self.displacement), ("node_coords", self.node_coords)):
                root.create_array(name, data=np.ascontiguousarray(arr, dtype=np.float64))
            if "element_size" in self.info:
                root.create_array("strain", data=np.ascontiguousarray(self.element_strain(), dtype=np.float64))
            for name, dtype in (("flags", np.uint8), ("brightness", np.float64), ("active", np.uint8),
                                ("uncertainty", np.float64)):
                if getattr(self, name) is not None:
                    root.create_array(name, data=np.ascontiguousarray(getattr(self, name), dtype=dtype))
            hist = root.create_group("history")
            for name in HISTORY_FIELDS:
                hist.create_array(name, data=np.asarray(self.history[name]))
            root.attrs["chunkdic"] = {**_jsonable(self.info), "kind": "result", "complete": True}
        self.path = str(path)


#: attributes every result holds (``open_result`` refuses a group without them)
REQUIRED_INFO = ("element_size", "roi", "final_gap")


def open_result(path: str | os.PathLike) -> Result:
    """Read a result written by :func:`chunkdic.correlate`.

    Refuses (one-line :class:`InputError`) a path that is not a result, an incomplete one
    (interrupted run), one whose attributes, arrays or history are missing or do not
    agree with each other, and a damaged store.
    """
    import zarr

    path = Path(path)
    if not path.exists():
        raise InputError(f"result {path} does not exist")
    try:
        root = zarr.open_group(str(path), mode="r")
        info = dict(root.attrs["chunkdic"])
    except Exception as exc:  # noqa: BLE001 - any failure means "not a result"
        raise InputError(f"{path} is not a chunkdic result ({exc.__class__.__name__})") from None
    if not info.get("complete", False):
        raise InputError(f"result {path} is incomplete (the run that wrote it was interrupted)")
    missing = [k for k in REQUIRED_INFO if k not in info]
    if missing:
        raise InputError(f"result {path} lacks the attribute(s) {', '.join(missing)}: not a chunkdic result, "
                         "or a damaged one")
    try:
        u = root["displacement"][...]
        X = root["node_coords"][...]
        history = {name: root["history"][name][...] for name in HISTORY_FIELDS}
        optional = {name: root[name][...] if name in root else None
                    for name in ("strain", "flags", "brightness", "active", "uncertainty")}
    except KeyError as exc:
        raise InputError(f"result {path} lacks the array {exc.args[0]!r}: a damaged result") from None
    except Exception as exc:  # noqa: BLE001 - undecodable chunks
        raise InputError(f"result {path} cannot be read ({type(exc).__name__}: {exc}"
                         .splitlines()[0] + "): a damaged result") from None
    _check_consistent(path, info, u, X, history)
    return Result(u, X, history, info, str(path), **optional)


def _check_consistent(path, info, u, X, history) -> None:
    """The arrays of a result agree with its attributes (else one-line InputError)."""
    try:
        ell = int(info["element_size"])
        roi = [(int(a), int(b)) for a, b in info["roi"]]
        nodes = tuple((b - a) // ell + 1 for a, b in roi)
        ok_roi = len(roi) == 3 and ell >= 1 and all((b - a) % ell == 0 and b > a for a, b in roi)
    except (TypeError, ValueError, KeyError):
        ok_roi, nodes = False, None
    if not ok_roi:
        raise InputError(f"result {path}: attributes element_size {info.get('element_size')!r} and roi "
                         f"{info.get('roi')!r} do not describe a mesh: a damaged result")
    for name, a in (("displacement", u), ("node_coords", X)):
        if a.shape != (3,) + nodes:
            raise InputError(f"result {path}: {name} has shape {a.shape}, the mesh needs {(3,) + nodes}: "
                             "a damaged result")
    lengths = {name: len(v) for name, v in history.items()}
    if len(set(lengths.values())) > 1:
        raise InputError(f"result {path}: history arrays of different lengths {lengths}: a damaged result")


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj
