"""A correlation result and its Zarr v3 group.

The group holds small arrays only (mesh-sized): ``displacement`` and ``node_coords``
``(3, nz, ny, nx)`` float64 in voxels of the correlated level, and the iteration history
``history/level``, ``history/iteration``, ``history/gap``, ``history/max_delta``,
``history/excluded``, and the element strains ``strain`` ``(3, 3, ez, ey, ex)`` float64
(dimensionless, :mod:`chunkdic.results.strain`; computed from ``displacement`` when the result
is saved, absent from results written before it existed). Everything else is in
``attrs["chunkdic"]``. The group is created with ``complete: false`` and marked complete
last, so an interrupted write is never mistaken for a result.

Every array carries Zarr v3 ``dimension_names`` and ``units`` / ``long_name`` attributes
(:data:`LAYOUT`), and the group holds the 1-D node and element-centre positions ``z, y,
x`` and ``ez, ey, ex`` as coordinate arrays, so that ``xarray.open_zarr(path)`` reads a
result as a labelled Dataset (``displacement`` on ``("component", "z", "y", "x")``).
Results written before this carry no dimension names: :meth:`Result.to_xarray` works on
every result.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..mesh import Mesh, level0_position
from .layout import FLAG_MASKED, FLAG_NO_DATA, FLAG_WEAK, HISTORY_FIELDS, HISTORY_LAYOUT, LAYOUT

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
        (paper section 5.1), ``max_delta`` = ``max |δa|`` of the update that followed
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
        :data:`FLAG_WEAK` (poorly textured, regularised, or not settled at the noise level) and :data:`FLAG_MASKED` (outside
        the specimen mask, NaN).
    active : ndarray, shape (ez, ey, ex), uint8, optional
        Elements that took part (a specimen mask's material elements, :mod:`chunkdic.passes.masks`);
        ``None`` without a mask.
    uncertainty : ndarray, shape (3, nz, ny, nx), float64, optional
        Standard deviation of each nodal displacement from the final residual's noise,
        voxels of ``level`` (:func:`chunkdic.method.noise.nodal_uncertainty`); NaN where not measured.
    brightness : ndarray, shape (2, ez, ey, ex), float64, optional
        Per-element gain and offset of the grey-level model (:mod:`chunkdic.method.brightness`):
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
    def level(self) -> int:
        """The pyramid level the field was computed on (its displacements are in its voxels)."""
        return int(self.info.get("level", 0))

    @property
    def scale(self) -> float:
        """Size of a voxel of :attr:`level` in level-0 voxels (``2 ** level``)."""
        return float(self.info.get("scale", 2.0**self.level))

    @property
    def voxel_size(self) -> tuple[float, float, float] | None:
        """Physical size of a level-0 voxel ``(z, y, x)`` in :attr:`unit`, if the reference carried one."""
        vs = self.info.get("voxel_size")
        return None if not vs else tuple(float(v) for v in vs)

    @property
    def unit(self) -> str | None:
        """Unit of :attr:`voxel_size` (an OME-NGFF unit name), if any."""
        return self.info.get("unit") if self.voxel_size is not None else None

    @property
    def mesh(self) -> Mesh:
        roi = self.info["roi"]
        ell = int(self.info["element_size"])
        return Mesh(tuple(int(a) for a, _ in roi), ell, tuple((b - a) // ell for a, b in roi))

    def element_strain(self, measure: str = "small") -> np.ndarray:
        """Element strains ``(3, 3, ez, ey, ex)``: the small strain stored (else computed and
        kept), or another measure of :mod:`chunkdic.results.strain` (``"green-lagrange"``), computed."""
        from .strain import check_measure, element_strain

        if check_measure(measure) != "small":
            return element_strain(self.displacement, self.info["element_size"], measure)
        if self.strain is None:
            self.strain = element_strain(self.displacement, self.info["element_size"])
        return self.strain

    def strain_summary(self, *, measure: str | None = None, exclude_outer: bool = True):
        """Mean strain over the ROI (paper 5.2, 5.4), what ``chunkdic strain`` prints.

        :func:`chunkdic.results.strain.strain_summary` of this result: Green–Lagrange by default
        (``measure="small"``: the paper's), without the outermost layer of elements, over the
        active elements of a mask. (Not ``Result.strain``: that name holds the element strains.)

        Returns
        -------
        chunkdic.results.strain.StrainSummary
            ``mean`` (3, 3), ``eps_zz``, ``principal``, ``max_rotation`` (degrees), ...; ``as_dict()``.

        Examples
        --------
        >>> s = chunkdic.open_result("result.zarr").strain_summary()  # doctest: +SKIP
        >>> s.eps_zz, s.principal  # doctest: +SKIP
        """
        from .strain import DEFAULT_MEASURE, strain_summary

        self.check_displacement()
        return strain_summary(self, exclude_outer=exclude_outer, measure=measure or DEFAULT_MEASURE)

    def check_displacement(self) -> None:
        """Refuse a result whose nodal field has NaN/inf values the result does not explain.

        A node flagged as not measured (``FLAG_NO_DATA``, ``FLAG_MASKED``) is NaN by design;
        any other non-finite value is damage (strains and exports would be garbage).

        Raises
        ------
        InputError
            One line naming the result and the first damaged node.
        """
        bad = (~np.isfinite(self.displacement)).any(axis=0)
        if self.flags is not None and self.flags.shape == bad.shape:
            bad &= (self.flags & (FLAG_NO_DATA | FLAG_MASKED)) == 0
        if bad.any():
            n = int(bad.sum())
            node = tuple(int(v) for v in np.argwhere(bad)[0])
            raise InputError(f"result {self.path}: {n} node(s) have no finite displacement (first: node {node}): "
                             "the result is damaged or was not measured there")

    def _arrays(self) -> dict[str, np.ndarray]:
        """Every array of the result group, by name (:data:`LAYOUT`), with the 1-D node and
        element-centre positions taken from the regular mesh."""
        X = self.node_coords
        arrays = {"displacement": self.displacement, "node_coords": X}
        if "element_size" in self.info:
            arrays["strain"] = self.element_strain()
        for name in ("flags", "brightness", "active", "uncertainty"):
            if getattr(self, name) is not None:
                arrays[name] = getattr(self, name)
        for axis, name in enumerate("zyx"):  # the mesh is regular: one position per node index
            line = X[(axis,) + tuple(slice(None) if a == axis else 0 for a in range(3))]
            arrays[name] = line
            arrays["e" + name] = (line[1:] + line[:-1]) / 2
        return arrays

    def _var_attrs(self, name: str, layout=None) -> dict:
        _, units, text = (layout or LAYOUT)[name]
        level = self.level
        long_name = text + (f" (voxels of level {level})" if units == "voxel" and level else "")
        return {"units": units, "long_name": long_name}

    def to_xarray(self):
        """The result as an :class:`xarray.Dataset` (xarray is an optional dependency).

        Returns
        -------
        xarray.Dataset
            ``displacement``, ``node_coords``, ``uncertainty`` on ``("component", "z",
            "y", "x")``, ``strain`` on ``("component_i", "component_j", "ez", "ey", "ex")``,
            ``flags``, ``active``, ``brightness`` when present, and the iteration history
            (``history_gap`` …) on ``("step",)``. Coordinates: ``component`` (``"z", "y",
            "x"``), node positions ``z, y, x`` and element centres ``ez, ey, ex`` in voxels
            of the correlated level; when the scan has a voxel size, also ``z_physical`` …
            (level-0 voxel centres times the voxel size, in ``unit``). Each variable has
            ``units`` and ``long_name`` attributes; the Dataset's attributes hold the
            scalar facts of the run (element size, level, status, gap, voxel size, unit).

        Examples
        --------
        >>> ds = chunkdic.open_result("result.zarr").to_xarray()  # doctest: +SKIP
        >>> ds.displacement.sel(component="z").isel(x=0).plot()  # doctest: +SKIP
        """
        try:
            import xarray as xr
        except ImportError:
            raise ImportError("Result.to_xarray needs xarray: pip install xarray") from None
        arrays = self._arrays()
        coords = {"component": ("component", np.array(["z", "y", "x"]))}
        data_vars = {}
        for name, arr in arrays.items():
            entry = (LAYOUT[name][0], np.asarray(arr), self._var_attrs(name))
            (coords if name in ("z", "y", "x", "ez", "ey", "ex") else data_vars)[name] = entry
        coords.update(self._physical_coords(arrays))
        for name, arr in self.history.items():
            data_vars["history_" + name] = (HISTORY_LAYOUT[name][0], np.asarray(arr),
                                            self._var_attrs(name, HISTORY_LAYOUT))
        return xr.Dataset(data_vars, coords=coords, attrs=self.summary_attrs())

    def voxel_length(self) -> np.ndarray | None:
        """Physical length of one voxel of the correlated level per axis ``(z, y, x)``, in
        ``info["unit"]`` (``scale`` level-0 voxels times the scan's voxel size); ``None``
        when the scan had no voxel size. A displacement in level voxels times this is a
        displacement in the physical unit."""
        if self.voxel_size is None:
            return None
        return self.scale * np.asarray(self.voxel_size, dtype=np.float64)

    def _physical_coords(self, arrays: dict) -> dict:
        """Node positions in the scan's physical unit, ``{"z_physical": ("z", …), …}``
        (empty without a voxel size)."""
        vs = self.voxel_size
        if vs is None:
            return {}
        scale = self.scale
        unit = self.unit or "unit"
        out = {}
        for axis, name in enumerate("zyx"):
            level0 = level0_position(arrays[name], scale)
            out[f"{name}_physical"] = (name, level0 * float(vs[axis]),
                                       {"units": unit, "long_name": f"node position along {name}"})
        return out

    def summary_attrs(self) -> dict:
        """Scalar facts of the run (JSON- and netCDF-friendly): element size, level, scale,
        status, gaps, voxel size and unit (when known), chunkdic version."""
        from .. import __version__

        keys = ("element_size", "level", "scale", "status", "converged", "initial_gap", "final_gap",
                "voxel_size", "unit")
        attrs = {k: jsonable(self.info[k]) for k in keys if self.info.get(k) is not None}
        if "converged" in attrs:
            attrs["converged"] = int(bool(attrs["converged"]))  # netCDF has no booleans
        attrs["chunkdic_version"] = self.info.get("chunkdic_version") or __version__
        return attrs

    def __repr__(self) -> str:
        i = self.info
        gap = i.get("final_gap")  # None: a field composed from others (chunkdic.series), no gap of its own
        return (
            f"<chunkdic.Result {self.displacement.shape[1:]} nodes, ell={i.get('element_size')} "
            f"level={i.get('level')} status={i.get('status')} final_gap={float('nan') if gap is None else gap:.4g}>"
        )

    def save(self, path: str | os.PathLike, *, overwrite: bool = False, inputs=()) -> None:
        """Write the result as a Zarr v3 group (complete flag set last).

        The group is written next to ``path`` and renamed into place when complete, so an
        existing result is replaced only by a complete one. ``overwrite`` replaces only a
        result that chunkdic wrote (:mod:`chunkdic.io.outputs`); ``inputs`` (paths) may not
        be, contain or hold ``path``.
        """
        import zarr

        from ..io.outputs import Outputs

        plan = Outputs(inputs=inputs, overwrite=overwrite)
        entry = plan.add(path, "result")
        with plan:
            root = zarr.open_group(str(entry.work), mode="w", zarr_format=3)
            root.attrs["chunkdic"] = {**jsonable(self.info), "kind": "result", "complete": False}
            for name, arr in self._arrays().items():
                dtype = np.uint8 if name in ("flags", "active") else np.float64
                root.create_array(name, data=np.ascontiguousarray(arr, dtype=dtype),
                                  dimension_names=LAYOUT[name][0], attributes=self._var_attrs(name))
            hist = root.create_group("history")
            for name in HISTORY_FIELDS:
                hist.create_array(name, data=np.asarray(self.history[name]), dimension_names=HISTORY_LAYOUT[name][0],
                                  attributes=self._var_attrs(name, HISTORY_LAYOUT))
            root.attrs["chunkdic"] = {**jsonable(self.info), "kind": "result", "complete": True}
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
    except (TypeError, ValueError, KeyError, ZeroDivisionError):  # element_size 0: no mesh
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


def jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def node_flags(mesh, elements: np.ndarray | None, weak_nodes, masked: np.ndarray | None = None) -> np.ndarray:
    """Per-node flags (:data:`chunkdic.results.result.FLAG_NO_DATA`, ``FLAG_WEAK``, ``FLAG_MASKED``), shape (nz, ny, nx) uint8.

    A node has no data when the elements around it together hold fewer valid voxels (voxels
    whose ``X + u(X)`` falls inside ``g``) than ``chunkdic.min-node-support`` of one element:
    its value would be extrapolated by its neighbours, not measured.
    """
    flags = np.zeros(mesh.nodes_shape, np.uint8)
    if elements is not None:
        valid = np.pad(elements[2], 1)
        support = sum(valid[dz:dz + flags.shape[0], dy:dy + flags.shape[1], dx:dx + flags.shape[2]]
                      for dz in (0, 1) for dy in (0, 1) for dx in (0, 1))
        flags[support < config.get("min-node-support") * mesh.element_size**3] |= FLAG_NO_DATA
    for n in weak_nodes:
        flags[tuple(n)] |= FLAG_WEAK
    if masked is not None:
        flags[masked] = FLAG_MASKED
    return flags
