"""Synthetic pairs on disk: reference and deformed scans of every specimen, standard cases.

One idea: write a reference / deformed pair (``ref.zarr``, ``def.zarr``, ``field.json``) of
the procedural foam (:mod:`chunkdic.synth.foam`) or of a CT-like specimen (:mod:`chunkdic.synth.ctpair`)
under an analytic field (:mod:`chunkdic.synth.fields`, re-exported here), the three standard test
cases, and read the pair's metadata back. docs/synthetic.md describes the specimens.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from .. import config
from ..errors import InputError
from ..io.owntree import remove
from ..io.scanwrite import write_scan_resumable
from ..io.kinds import kind_of
from .ctpair import CTSpecimen, as_dask_ct, fourier_deformed, standard_field
from .fields import Affine, Band, Composed, Crack, Field, Star, Translation, true_displacement
from .foam import (
    INT_HI,
    INT_LO,
    TextureParams,
    as_dask,
    check_dtype,
    shape3,
    texture_params,
)
from .microstructure import specimen_params
from .shear import Slip, Wave

__all__ = [
    "Field",
    "Translation",
    "Affine",
    "Band",
    "Star",
    "Crack",
    "Composed",
    "Wave",
    "Slip",
    "synthesize",
    "true_displacement",
    "load_field",
    "load_metadata",
    "load_texture",
    "load_specimen",
    "standard_case",
]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- writer

_SYNTH_ATTR = "synthetic"


def _metadata(field, p: TextureParams, shape, dtype, noise) -> dict:
    return {
        "field": None if field is None else field.to_json(),
        "texture": p.to_json(),
        "seed": p.seed,
        "shape": list(shape),
        "dtype": np.dtype(dtype).name,
        "noise": float(noise),
        "intensity_map": None if np.dtype(dtype).kind == "f" else [INT_LO, INT_HI],
    }


SPECIMEN_NAMES = ("foam", "grains", "concrete")
_CT_ONLY = ("angles", "filter", "blur", "rings", "gain", "offset", "drift", "mode", "imaging", "texture_scale")


def synthesize(out_dir, shape, *, field: Field | None = None, specimen: str = "foam",
               seed: int = 0, dtype=None, chunks=None, voxel_size=None, unit=None,
               levels: int = 0, overwrite: bool = False, progress=None,
               cell_size: float = 8.0, bead_size: float = 64.0, noise: float | None = None,
               fourier_shift: bool = False, resume: bool = False, **params) -> dict:
    """Write a synthetic reference/deformed pair ``out_dir/ref.zarr``, ``out_dir/def.zarr``.

    Both scans are written chunk by chunk, in place, with
    :func:`chunkdic.io.scanwrite.write_scan_resumable`. The field
    JSON, seed and specimen parameters go to ``attrs["chunkdic"]["synthetic"]`` of both
    groups and to ``out_dir/field.json`` (written last: its presence marks a complete pair).

    Parameters
    ----------
    out_dir : path
        Output directory (created).
    shape : int or tuple of 3 int
        Scan shape ``(nz, ny, nx)``.
    field : Field or None
        Displacement field (``None``: a pair of identical scans up to ``noise``).
    specimen : {"foam", "grains", "concrete"} or GrainsParams or ConcreteParams
        ``foam`` (default): the smooth procedural foam of :mod:`chunkdic.synth.foam`. ``grains`` /
        ``concrete``: sharp-edged CT-like specimens imaged by simulated CT slice by slice
        (:mod:`chunkdic.synth.microstructure`, :mod:`chunkdic.synth.ctsim`, docs/synthetic.md).
    dtype : str
        Foam: ``uint8`` (default), ``uint16`` or ``float32``; integer grey levels are
        rounded, so ``g(X + u(X)) = f(X)`` holds to half a grey level. CT specimens:
        ``uint16`` (default; phase units ``[-0.5, 1.5]`` over the range) or ``float32``.
    chunks, voxel_size, unit, levels, overwrite, progress
        Passed to the scan writer.
    seed, cell_size, bead_size
        Foam texture parameters (see :func:`chunkdic.synth.foam.render`); ``seed`` for every specimen.
    noise : float, optional
        Foam: std of additive Gaussian noise, texture units (default 0). CT specimens:
        std of the reconstruction noise as a fraction of the phase contrast (default 0.02),
        independent in the two scans.
    fourier_shift : bool
        CT specimens: the deformed scan is the stored reference translated by a Fourier
        phase shift of ``field.t`` (a :class:`Translation`; the paper's section 4.2 test).
    resume : bool
        Continue an interrupted write of the same pair in ``out_dir`` (no ``field.json``
        yet): chunks already stored complete are kept, the rest written; the result equals
        an uninterrupted run bit for bit. Scans written with other settings are refused.
    **params
        Foam: other :class:`TextureParams` fields. CT specimens: specimen parameters
        (:class:`~chunkdic.synth.microstructure.GrainsParams`, ``ConcreteParams``; among them
        ``texture_scale``, the factor on every size of the microstructure: about 6 voxels of
        autocorrelation length at 1, docs/synthetic.md "Texture scale"), imaging
        (``imaging="fbp"`` or ``"local"``, :mod:`chunkdic.synth.ctlocal`; ``angles``, ``filter``,
        ``blur``, ``rings``) and the grey-level change of the
        deformed scan (``gain``, ``offset``, ``drift``; :class:`~chunkdic.synth.ctsim.GreyChange`).

    Returns
    -------
    dict
        ``{"reference": path, "deformed": path, "field_json": path, "field": Field,
        "texture": TextureParams or specimen parameters}``.

    Examples
    --------
    Case (c) of docs/synthetic.md, a compression band with a grey-level change:

    >>> from chunkdic.synth.ctpair import standard_field
    >>> fld, _ = standard_field("band", (96, 96, 96))
    >>> synthesize("band", 96, specimen="grains", field=fld, noise=0.02,
    ...            gain=1.1, offset=0.05, drift=0.03)  # doctest: +SKIP
    """

    shape = shape3(shape)
    if chunks is None:
        chunks = config.get("chunk-size")
    if specimen == "foam":
        bad = sorted(k for k in params if k in _CT_ONLY) + (["fourier_shift"] if fourier_shift else [])
        if bad:
            raise InputError(f"{', '.join(bad)}: only for the CT specimens (grains, concrete)")
        p = texture_params(seed, cell_size, bead_size, params)
        dt = check_dtype("uint8" if dtype is None else dtype)
        noise = 0.0 if noise is None else float(noise)
        if not (np.isfinite(noise) and noise >= 0):
            raise InputError(f"noise must be >= 0, got {noise!r}")
        meta = _metadata(field, p, shape, dt, noise)

        def make(which, ref_path, scratch):
            return as_dask(shape, chunks=chunks, field=field, seed=p, which=which, dtype=dt,
                           noise=noise)
    else:

        p = CTSpecimen.build(specimen, shape, seed=seed, field=field, dtype=dtype,
                             fourier_shift=fourier_shift, noise=noise, **params)
        dt = np.dtype(p.dtype)
        meta = {"field": None if field is None else field.to_json(), "seed": p.params.seed,
                "shape": list(shape), "dtype": dt.name, "noise": p.imaging.noise,
                **p.metadata()}

        def make(which, ref_path, scratch):
            if which == "deformed" and p.fourier_shift:
                arr, tmp = fourier_deformed(ref_path, os.path.dirname(ref_path), p)
                scratch.append(tmp)
                return arr
            return as_dask_ct(p, which, chunks)
    out = _write_pair(out_dir, shape, make, meta, chunks=chunks, voxel_size=voxel_size,
                      unit=unit, levels=levels, overwrite=overwrite, progress=progress, resume=resume)
    return {**out, "field": field, "texture": p if specimen == "foam" else p.params}


def standard_case(out_dir, case: str, shape=128, *, specimen: str = "grains", **kw) -> dict:
    """Write one of the three standard test pairs in one call (docs/synthetic.md).

    ``case``: ``"fourier-shift"`` (the paper's section 4.2 test: deformed = reference
    Fourier-shifted by (0.5, 0.5, 0.5) voxel), ``"shift"`` (the same translation rendered
    from the geometry, independent noise in each scan) or ``"band"`` (compression band at
    mid-height: -8 % peak strain, 6 voxels wide, lateral expansion 0.3). ``kw`` goes to
    :func:`synthesize` (``noise``, ``gain``, ``offset``, ``drift``, ``seed``, ``dtype``,
    specimen and imaging parameters, ...).

    Examples
    --------
    >>> standard_case("band128", "band", 128, noise=0.02, gain=1.1, offset=0.05,
    ...               drift=0.03)  # doctest: +SKIP
    """

    shape = shape3(shape)
    fld, fourier = standard_field(case, shape)
    return synthesize(out_dir, shape, field=fld, specimen=specimen, fourier_shift=fourier, **kw)


def _write_pair(out_dir, shape, make, meta, *, chunks, voxel_size, unit, levels, overwrite,
                progress, resume=False) -> dict:
    """Write ``make(which, ref_path, scratch)`` for both scans, then ``field.json``.

    ``resume``: ``out_dir`` is an interrupted pair of the same request (a synthetic pair
    folder marked incomplete, held by the caller's :class:`~chunkdic.io.outputs.Outputs`):
    the scans are written in place and their chunks already stored complete are kept
    (:func:`chunkdic.io.scanwrite.write_scan_resumable`). Without it, existing scans are
    refused unless ``overwrite``.
    """

    out_dir = os.fspath(out_dir)
    ref, dfm = os.path.join(out_dir, "ref.zarr"), os.path.join(out_dir, "def.zarr")
    fjson = os.path.join(out_dir, "field.json")
    existing = [q for q in (ref, dfm, fjson) if os.path.exists(q)]
    if os.path.exists(fjson) and resume and not overwrite:
        raise InputError(f"{out_dir} is a complete synthetic pair: nothing to resume")
    if existing and not overwrite and not resume:
        raise InputError(f"{existing[0]} exists (use overwrite=True / --overwrite)")
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise InputError(f"{out_dir} exists and is not a directory")
    os.makedirs(out_dir, exist_ok=True)
    if os.path.exists(fjson):
        remove(fjson)  # the pair is incomplete until field.json is back
    if overwrite:
        for path in (ref, dfm):
            if os.path.exists(path):
                if kind_of(Path(path))[0] != "scan":  # never a store chunkdic did not write
                    raise InputError(f"{path} is not a scan chunkdic wrote: refusing to replace it")
                remove(path)
    # scans this call began (removed on failure); a resumed scan was there before: kept
    written, scratch = [], []
    try:
        for i, (which, path) in enumerate((("reference", ref), ("deformed", dfm))):
            arr = make(which, ref, scratch)
            log.info("writing %s scan %s, shape %s, %s", which, path, shape, arr.dtype)
            sub = None if progress is None else _sub_progress(progress, i / 2.0, (i + 1) / 2.0)
            if not os.path.exists(path):
                written.append(path)
            write_scan_resumable(path, arr, attrs={_SYNTH_ATTR: {**meta, "role": which}}, voxel_size=voxel_size, unit=unit, chunks=chunks, levels=levels, progress=sub)
        tmp = fjson + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(meta, fh, indent=2)
        os.replace(tmp, fjson)
    except BaseException:
        for path in written:  # leave no half-written pair behind
            remove(path)
        raise
    finally:
        for path in scratch:
            remove(path)
    return {"reference": ref, "deformed": dfm, "field_json": fjson}


def _sub_progress(progress, start: float, end: float):
    def report(frac: float) -> None:
        progress(start + (end - start) * float(frac))

    return report


def load_metadata(path) -> dict:
    """Synthetic metadata of a pair directory (``field.json``) or of one scan group."""
    path = os.fspath(path)
    fj = os.path.join(path, "field.json")
    if os.path.isfile(fj):
        with open(fj) as fh:
            return json.load(fh)
    if os.path.isfile(path) and path.endswith(".json"):
        with open(path) as fh:
            return json.load(fh)
    try:
        import zarr

        g = zarr.open_group(path, mode="r")
        return dict(g.attrs["chunkdic"][_SYNTH_ATTR])
    except Exception as exc:  # noqa: BLE001 - turned into one actionable line
        raise InputError(f"{path} is not a synthetic pair directory or scan ({exc})") from None


def load_field(path) -> Field | None:
    """The displacement field of a synthetic pair (directory, ``field.json`` or scan group).

    Returns ``None`` for a pair written without a field.
    """
    d = load_metadata(path)["field"]
    return None if d is None else Field.from_json(d)


def load_texture(path) -> TextureParams:
    """The texture parameters of a synthetic foam pair (directory, ``field.json`` or scan group)."""
    meta = load_metadata(path)
    if "texture" not in meta:
        raise InputError(f"{path} is a {meta.get('specimen', {}).get('specimen')} pair, not a foam")
    return TextureParams(**meta["texture"])


def load_specimen(path):
    """The specimen of a synthetic pair: :class:`TextureParams` (foam) or the parameters
    of a CT specimen (:class:`~chunkdic.synth.microstructure.GrainsParams`, ``ConcreteParams``)."""
    meta = load_metadata(path)
    if "texture" in meta:
        return TextureParams(**meta["texture"])

    return specimen_params(dict(meta["specimen"]))
