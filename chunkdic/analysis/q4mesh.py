"""The inputs of the Q4 correlation: 2-D images and their Q4 meshes, level by level.

One idea: what :mod:`chunkdic.analysis.q4` correlates on, with the engine's conventions one axis
less (:mod:`chunkdic.analysis.q4` explains them): :class:`Mesh2D`, the regular Q4 mesh of a box ROI
of whole elements (bilinear shape functions at the pixel centres, field evaluation);
:func:`plan2d`, the mesh of each pyramid level (the rules of
:func:`chunkdic.engine.meshes.plan_meshes`); :func:`pyramid2d`, the 2×2 sum pyramid of an image;
:func:`read_image`, a 2-D grey image from a file. In memory: a 2-D image is small.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..engine.meshes import MIN_COARSE_EDGE, box_at_level, default_margin
from ..errors import InputError

__all__ = ["Mesh2D", "plan2d", "pyramid2d", "read_image"]


@dataclass(frozen=True)
class Mesh2D:
    """Regular Q4 mesh over a box ROI of whole elements (one pyramid level).

    Parameters
    ----------
    origin : tuple of 2 int
        First ROI pixel ``(y, x)``, pixels of the level.
    element_size : int
        Element edge ``ell``, pixels of the level.
    shape : tuple of 2 int
        Elements per axis.
    """

    origin: tuple[int, int]
    element_size: int
    shape: tuple[int, int]

    @property
    def nodes_shape(self) -> tuple[int, int]:
        return tuple(n + 1 for n in self.shape)

    @property
    def roi(self) -> tuple[slice, slice]:
        ell = self.element_size
        return tuple(slice(o, o + n * ell) for o, n in zip(self.origin, self.shape))

    def node_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Node coordinates along ``y`` and ``x``, ``origin + k ell - 0.5`` (pixels)."""
        ell = self.element_size
        return tuple(o + ell * np.arange(n + 1) - 0.5 for o, n in zip(self.origin, self.shape))

    def node_coords(self) -> np.ndarray:
        """Node positions, shape ``(2, ny, nx)``, float64, pixels of the level."""
        return np.stack(np.meshgrid(*self.node_axes(), indexing="ij"))

    def shape_matrix(self) -> sp.csr_matrix:
        """Bilinear shape functions at the ROI pixel centres: ``(Ly Lx, ny nx)`` sparse.

        Row ``i Lx + j`` is ROI pixel ``(i, j)``, column ``ky nx + kx`` node ``(ky, kx)``;
        a field's pixel values are ``Phi @ a.ravel()``. The Q4 table is the outer product
        of two 1-D hat tables (``xi = (l + 0.5) / ell``), hence the Kronecker product.
        """
        return sp.kron(*(_hat(self.element_size, n) for n in self.shape), format="csr")

    def evaluate(self, u: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The Q4 field at arbitrary points (bilinear, linearly extended outside the mesh).

        Parameters
        ----------
        u : ndarray, shape (k, ny, nx), float64
            Nodal values.
        points : ndarray, shape (2, ...), float64, pixels of the level

        Returns
        -------
        ndarray, shape (k, ...), float64
        """
        idx, frac = [], []
        for axis in range(2):
            t = (points[axis] - (self.origin[axis] - 0.5)) / self.element_size
            k = np.clip(np.floor(t), 0, self.shape[axis] - 1).astype(np.int64)
            idx.append(k)
            frac.append(t - k)
        out = np.zeros((u.shape[0],) + points.shape[1:])
        for dy in (0, 1):
            for dx in (0, 1):
                w = (frac[0] if dy else 1 - frac[0]) * (frac[1] if dx else 1 - frac[1])
                out += w * u[:, idx[0] + dy, idx[1] + dx]
        return out


def _hat(ell: int, n_elements: int) -> sp.csr_matrix:
    """1-D linear shape functions at the pixel centres of ``n_elements`` elements: ``(n ell, n + 1)``."""
    xi = (np.arange(ell) + 0.5) / ell
    rows = np.arange(n_elements * ell)
    k = rows // ell
    w = np.tile(xi, n_elements)
    return sp.csr_matrix((np.concatenate([1 - w, w]), (np.concatenate([rows, rows]), np.concatenate([k, k + 1]))),
                         shape=(n_elements * ell, n_elements + 1))


def pyramid2d(img: np.ndarray, levels: int) -> list[np.ndarray]:
    """Levels ``0 … levels`` of the 2×2 sum pyramid (odd sizes trimmed), float64."""
    out = [np.asarray(img, np.float64)]
    for _ in range(levels):
        a = out[-1]
        a = a[: a.shape[0] // 2 * 2, : a.shape[1] // 2 * 2]
        out.append(a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2])
    return out


def _roi_box(roi, shape, ell: int) -> tuple[tuple[int, int], tuple[int, int]]:
    if roi is None:
        m = default_margin(ell)
        return tuple((m, n - m) for n in shape)
    if isinstance(roi, str):
        try:
            roi = [tuple(int(v) for v in part.split(":")) for part in roi.split(",")]
        except ValueError:
            raise InputError(f"ROI {roi!r}: expected y0:y1,x0:x1 with integer bounds") from None
    pairs = [(s.start, s.stop) if isinstance(s, slice) else tuple(s) for s in roi]
    if len(pairs) != 2 or any(len(p) != 2 for p in pairs):
        raise InputError(f"ROI {roi!r}: expected two ranges y0:y1,x0:x1")
    for axis, ((a, b), n) in enumerate(zip(pairs, shape)):
        if a is None or b is None or not 0 <= a < b <= n:
            raise InputError(f"ROI {a}:{b} on axis {'yx'[axis]} is empty or outside the image (0:{n})")
    return tuple((int(a), int(b)) for a, b in pairs)


def _centred(box, ell: int) -> Mesh2D | None:
    n = tuple((b - a) // ell for a, b in box)
    if min(n) < 1:
        return None
    return Mesh2D(tuple(a + ((b - a) - k * ell) // 2 for (a, b), k in zip(box, n)), ell, n)


def plan2d(shape, element_size: int, roi=None, coarsest: int | None = None) -> dict[int, Mesh2D]:
    """Q4 meshes per pyramid level, level 0 first (the rules of :func:`chunkdic.engine.meshes.plan_meshes`)."""
    ell = int(element_size)
    mesh = _centred(_roi_box(roi, shape, ell), ell)
    if mesh is None:
        raise InputError(f"element size {ell} does not fit in the ROI of the {shape[0]}x{shape[1]} image: "
                         "choose a smaller element size or a larger ROI")
    meshes = {0: mesh}
    box0 = tuple((r.start, r.stop) for r in mesh.roi)
    top = 3 if coarsest is None else int(coarsest)
    for s in range(1, top + 1):
        box = box_at_level(box0, 2**s)
        edge = min(b - a for a, b in box)
        if edge < (MIN_COARSE_EDGE if coarsest is None else 2):
            if coarsest is not None:  # asked for, as the 3-D engine refuses it (engine.meshes)
                raise InputError(f"coarsest level {coarsest} is too coarse for this ROI (edge {edge} pixels at "
                                 f"level {s})")
            break
        meshes[s] = _centred(box, min(ell, edge))
    return meshes


def read_image(path) -> np.ndarray:
    """A 2-D grey image from ``.npy``, TIFF or any format Pillow reads (PNG, ...).

    A colour image whose channels are equal (grey saved as RGB) is read as its first
    channel; a true colour image, a stack or a missing file is refused (one-line
    :class:`InputError`).

    Returns
    -------
    ndarray, shape (ny, nx), the file's dtype
    """
    import os

    p = os.fspath(path)
    if not os.path.isfile(p):
        raise InputError(f"image {p} does not exist" if not os.path.exists(p) else f"image {p} is not a file")
    ext = os.path.splitext(p)[1].lower()
    try:
        if ext == ".npy":
            a = np.load(p, allow_pickle=False)
        elif ext in (".tif", ".tiff"):
            import tifffile

            a = tifffile.imread(p)
        else:
            from PIL import Image

            with Image.open(p) as im:
                a = np.asarray(im)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad input file
        raise InputError(f"image {p} cannot be read ({type(exc).__name__}: {exc})".splitlines()[0]) from None
    a = np.squeeze(a)
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        if not all(np.array_equal(a[..., 0], a[..., c]) for c in (1, 2)):
            raise InputError(f"image {p} is a colour image: convert it to grey levels first")
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(f"image {p} has shape {a.shape}: expected one 2-D grey image")
    return a
