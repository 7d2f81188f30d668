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
import shutil
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

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> None:
        """Write the result as a Zarr v3 group (complete flag set last)."""
        import zarr

        path = Path(path)
        check_output(path, overwrite=overwrite)
        if path.exists():
            shutil.rmtree(path)
        root = zarr.open_group(str(path), mode="w", zarr_format=3)
        root.attrs["chunkdic"] = {**_jsonable(self.info), "complete": False}
        for name, arr in (("displacement", self.displacement), ("node_coords", self.node_coords)):
            root.create_array(name, data=np.ascontiguousarray(arr, dtype=np.float64))
        if "element_size" in self.info:
            root.create_array("strain", data=np.ascontiguousarray(self.element_strain(), dtype=np.float64))
        if self.flags is not None:
            root.create_array("flags", data=np.ascontiguousarray(self.flags, dtype=np.uint8))
        if self.brightness is not None:
            root.create_array("brightness", data=np.ascontiguousarray(self.brightness, dtype=np.float64))
        if self.active is not None:
            root.create_array("active", data=np.ascontiguousarray(self.active, dtype=np.uint8))
        if self.uncertainty is not None:
            root.create_array("uncertainty", data=np.ascontiguousarray(self.uncertainty, dtype=np.float64))
        hist = root.create_group("history")
        for name in HISTORY_FIELDS:
            hist.create_array(name, data=np.asarray(self.history[name]))
        root.attrs["chunkdic"] = {**_jsonable(self.info), "complete": True}
        self.path = str(path)


def check_output(path: str | os.PathLike, *, overwrite: bool) -> None:
    """Refuse to replace an existing path unless ``overwrite`` (raises InputError)."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError(f"output {path} exists: choose another path or pass --overwrite")


def open_result(path: str | os.PathLike) -> Result:
    """Read a result written by :func:`chunkdic.correlate` (refuses incomplete ones)."""
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
    history = {name: root["history"][name][...] for name in HISTORY_FIELDS}
    optional = {name: root[name][...] if name in root else None
                for name in ("strain", "flags", "brightness", "active", "uncertainty")}
    return Result(root["displacement"][...], root["node_coords"][...], history, info, str(path), **optional)


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
