"""Checkpoints: a correlation survives the death of its client.

While it runs, a correlation keeps its output group marked incomplete and writes, after
every completed iteration, what it needs to continue: the Gauss–Newton state of the
current level (nodal field, best field so far, counters), the history, the rigid
translation and the statuses of the finished levels. Re-running the same command finds
the checkpoint, checks that inputs and settings are the same (a fingerprint) and carries
on from there; ``M`` and the B-spline coefficients are recomputed (deterministic), so the
final field equals that of an uninterrupted run to float round-off.

Layout inside ``OUT.zarr``: ``attrs["chunkdic"] = {"complete": false, "fingerprint": …,
"checkpoint": {…scalars…, "slot": k}}`` and arrays ``checkpoint/<name><k>``. Arrays are
written to the slot not in use before the attributes point at it, so a kill during a
checkpoint leaves the previous one intact.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import uuid
from pathlib import Path

import numpy as np

from ..errors import DiskSpaceError, InputError
from ..io.formats.detect import is_foreign
from ..io.integrity import content_identity
from ..io.kinds import kind_of
from ..results.result import open_result
from .initial import init_identity
from .meshes import parse_roi


def fingerprint(description: dict) -> str:
    """A stable hash of what determines a run's result (inputs and settings)."""
    text = json.dumps(description, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _read_attrs(path: Path) -> dict | None:
    import zarr

    try:
        return dict(zarr.open_group(str(path), mode="r").attrs.get("chunkdic", {}))
    except Exception:  # noqa: BLE001 - anything unreadable is "not ours"
        return None


def _what_changed(before: dict | None, now: dict | None) -> str:
    changed = [role for role in (now or {}) if before and role in before and before[role] != now[role]]
    return f" (the {' and '.join(changed)} scan changed since)" if changed else ""


class Checkpoint:
    """The checkpoint of one run in its output group."""

    def __init__(self, path: Path, print_: str):
        self.path = Path(path)
        self.fingerprint = print_
        self.saved = False  # whether this run has written a checkpoint yet

    @classmethod
    def start(cls, path, print_: str, *, identities: dict | None = None) -> tuple["Checkpoint", dict | None]:
        """Open the output for a run: fresh, or resumed from a matching checkpoint.

        The caller has checked the output (:mod:`chunkdic.io.outputs`: not an input, ours,
        ``--overwrite`` rules) and holds its lock (:class:`chunkdic.io.ownership.OutputLock`);
        here, under the lock, an existing group is read again. Returns the checkpoint and
        the saved state (``None`` for a fresh run). Refuses (InputError) a result completed
        meanwhile and a run made with other inputs or settings, naming the input whose
        content changed (``identities``: input role -> content identity).
        """
        import zarr

        path = Path(path)
        identities = json.loads(json.dumps(identities or {}, default=str))  # compared with their JSON form
        state = None
        if path.exists():
            attrs = _read_attrs(path)
            if attrs is None or "fingerprint" not in attrs:
                raise InputError(f"output {path} exists: choose another path or pass --overwrite")
            if attrs.get("complete"):
                raise InputError(f"output {path} is a complete result: choose another path or "
                                 "pass --overwrite")
            if attrs["fingerprint"] != print_:
                raise InputError(f"output {path} holds an interrupted run made with other inputs or settings"
                                 f"{_what_changed(attrs.get('identities'), identities)}: pass --overwrite to start "
                                 "again")
            state = attrs.get("checkpoint")
        else:
            root = zarr.open_group(str(path), mode="w", zarr_format=3)
            root.attrs["chunkdic"] = {"kind": "result", "complete": False, "fingerprint": print_,
                                      "identities": identities}
        ckpt = cls(path, print_)
        if state is not None:
            state = dict(state, arrays=ckpt._load_arrays(state))
        return ckpt, state

    def _load_arrays(self, state: dict) -> dict[str, np.ndarray]:
        import zarr

        try:
            group = zarr.open_group(str(self.path / "checkpoint"), mode="r")
            k = state["slot"]
            arrays = {name: group[f"{name}{k}"][...] for name in state["array_names"]}
            if not all(np.isfinite(a).all() for name, a in arrays.items() if name in ("u", "m_start")):
                raise ValueError("non-finite nodal field")
            return arrays
        except Exception as exc:  # noqa: BLE001 - garbled arrays or attributes: never a traceback, never a guess
            first = (str(exc).splitlines() or [""])[0]
            raise InputError(f"output {self.path} holds a checkpoint that cannot be read ({type(exc).__name__}: "
                             f"{first}): pass --overwrite to start again") from None

    def save(self, state: dict, arrays: dict[str, np.ndarray]) -> None:
        """Write a new checkpoint (arrays first, into the free slot, then the pointer)."""
        import zarr

        root = zarr.open_group(str(self.path), mode="r+")
        attrs = dict(root.attrs["chunkdic"])
        slot = 1 - attrs.get("checkpoint", {}).get("slot", 1)
        group = root.require_group("checkpoint")
        for name, arr in arrays.items():
            arr = np.ascontiguousarray(arr)
            # named dimensions, as every array of a result group (xarray reads them)
            group.create_array(f"{name}{slot}", data=arr, overwrite=True,
                               dimension_names=tuple(f"{name}_{i}" for i in range(arr.ndim)))
        attrs["checkpoint"] = {**state, "slot": slot, "array_names": sorted(arrays)}
        root.attrs["chunkdic"] = attrs
        self.saved = True


def completed_already(path, print_: str):
    """The complete result at ``path`` if this very run made it (same fingerprint: inputs,
    their contents, settings, ROI, start field), else None. A re-run of the same command
    (a batch job re-queued after a kill that landed just after the save) then has nothing
    to do, as ``make``."""

    p = Path(path)
    try:
        if p.is_symlink() or kind_of(p) != ("result", True):
            return None
    except OSError:  # a name too long, a loop of links: not this run's result (the output checks say why)
        return None
    attrs = _read_attrs(p)
    if attrs is None or attrs.get("fingerprint") != print_:
        return None
    return open_result(p)


def kept_checkpoint_error(exc: OSError, output) -> InputError:
    """The one line for a disk error (full, read-only, I/O) met after a checkpoint was saved:
    the checkpoint stays (marked incomplete) and the same command resumes from it."""
    where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
    cause = f"{exc.strerror or exc}{where}"
    return DiskSpaceError(f"{cause}; the checkpoint in {output} is kept (marked incomplete): "
                          "free space and run the same command again to resume, or remove it", cause=cause, kept=True)


def identify_input(src, scan) -> dict:
    """What identifies an input for resuming: path, shape, dtype and a cheap content
    identity of every stored level (:func:`chunkdic.io.integrity.content_identity`: chunk
    list, sizes, times and a fixed sample of chunk bytes, never the scan). In-memory
    inputs never match (no resume)."""
    if isinstance(src, (str, Path)) and is_foreign(src):
        # a TIFF or HDF5 file read in place (a mask, chunkdic.io.formats.open_any): its files'
        # sizes and modification times
        p = Path(scan.path)
        files = sorted(p.iterdir()) if p.is_dir() else [p]
        stat = [(f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in files if f.is_file()]
        return {"path": str(p.resolve()), "shape": scan.shape(0), "dtype": str(scan.dtype(0)),
                "content": {"files": stat}}
    if isinstance(src, (str, Path)):
        content = {str(s): content_identity(r.kind, r.path, r.key) for s, r in sorted(scan.stored_refs().items())}
        return {"path": str(Path(src).resolve()), "shape": scan.shape(0), "dtype": str(scan.dtype(0)),
                "content": content}
    return {"in-memory": uuid.uuid4().hex}


@dataclasses.dataclass(frozen=True)
class RunIdentity:
    """What identifies a run for resuming and in its result.

    Attributes
    ----------
    inputs : dict
        Per role (``reference``, ``deformed``, ``mask``), :func:`identify_input`.
    init : dict, optional
        The earlier result's identity (:func:`chunkdic.engine.initial.init_identity`).
    fingerprint : str
        The hash of the inputs, the settings, the ROI and the start field (:func:`fingerprint`).
    """

    inputs: dict
    init: dict | None
    fingerprint: str

    @property
    def resumable(self) -> bool:
        """Every input is on disk: an in-memory input's identity is random, such a run never resumes."""
        return not any("in-memory" in i for i in [*(i for i in self.inputs.values() if i is not None),
                                                   self.init or {}])


def identify_run(spec, ref, deformed, mask=None) -> RunIdentity:
    """The :class:`RunIdentity` of the run ``spec`` (:class:`chunkdic.engine.front.RunSpec`) of
    ``ref`` and ``deformed`` (as given: paths or arrays) and a ``mask``."""
    inputs = {role: identify_input(src, scan) for role, src, scan in
              (("reference", ref, spec.f_scan), ("deformed", deformed, spec.g_scan))}
    if mask is not None:
        inputs["mask"] = identify_input(mask, spec.mask_scan)
    described = {"settings": spec.settings.to_json(), "roi": parse_roi(spec.roi),
                 "inputs": [inputs["reference"], inputs["deformed"]], "mask": inputs.get("mask")}
    init_id = None
    if spec.init is not None:  # absent otherwise: fingerprints of runs without init are unchanged
        init_id = described["init"] = init_identity(spec.init)
        if spec.init.path is None:  # an in-memory result never resumes, as in-memory scans
            init_id["in-memory"] = uuid.uuid4().hex
    return RunIdentity(inputs, init_id, fingerprint(described))
