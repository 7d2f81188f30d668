"""The texture-dependent part of the multiscale schedule: the length each level starts with.

Every level iterates first under a curvature penalty of a starting length, and the
correlated level then chooses its own length around the field it converged to there
(:func:`chunkdic.solve.regchoice.choose_length`). On a texture that the elements resolve
(an autocorrelation length at most about ℓ: the granular and cementitious CT specimens,
6 voxels) the starting length is :data:`START_LENGTH` elements. On a coarse texture
(autocorrelation length of 12–24 voxels at ℓ = 8 or 6) many elements hold no edge at all:
under a 2ℓ penalty the field fits what the imaging does not carry with the material (the
partial volume and the detector's blur, which do not deform with it; the noise) and
settles 0.05–0.5 voxel off; the choice, linearised around that field, then keeps a short
length (16–32 voxels) and the run converges there, although the same data at a long
length give 0.002–0.005 voxel (20 % compression, docs/engine.md, "Large deformations on
coarse textures"). So the starting length grows with the square of the texture's scale in
elements: ``START_LENGTH ℓ (A / ℓ)²`` for an autocorrelation length ``A > ℓ``, on the
grid of the choice's candidates (:data:`~chunkdic.solve.regchoice.CANDIDATES`), at most
its longest; below ℓ = :data:`FINE_TEXTURE` the ratio is taken to that length instead
(a fine texture at ℓ = 4 keeps its 2ℓ: a longer start made its band's error 33 % worse).

The autocorrelation length is measured once per run, on the correlated level, by one task
that reads a few sampled blocks of the reference (:func:`texture_task`): the client never
touches voxels, and a 2048³ scan costs the same few megabytes as a 96³ one.
"""

from __future__ import annotations

import math

import numpy as np

from ..io.handles import ArrayRef
from ..mesh import Mesh
from ..solve.regchoice import CANDIDATES
from .events import emit

#: the regularisation length a level starts with on a texture its elements resolve, in elements
START_LENGTH = 2.0
#: an autocorrelation length (voxels) up to which a texture counts as fine at any element size:
#: the CT specimens' 5.5-6.4 voxels at ℓ = 4 kept their band's error only with a 2ℓ start
FINE_TEXTURE = 8.0
#: edge (voxels) of the blocks the autocorrelation length is measured on, and how many per axis
SAMPLE_EDGE = 64
SAMPLES_PER_AXIS = 2


def sample_boxes(roi: tuple[slice, slice, slice], edge: int = SAMPLE_EDGE) -> list[tuple[slice, slice, slice]]:
    """Blocks of at most ``edge`` voxels per axis centred on the ROI's quarters
    (:data:`SAMPLES_PER_AXIS` per axis, overlapping on an axis shorter than two blocks; one
    block on an axis no longer than one), moved inside the ROI: where the texture is measured."""
    per_axis = []
    for s in roi:
        n = s.stop - s.start
        e = min(edge, n)
        centres = [n / 2] if n <= e else [n * (2 * k + 1) / (2 * SAMPLES_PER_AXIS) for k in range(SAMPLES_PER_AXIS)]
        starts = sorted({min(max(int(round(c - e / 2)), 0), n - e) for c in centres})
        per_axis.append([slice(s.start + a, s.start + a + e) for a in starts])
    return [(z, y, x) for z in per_axis[0] for y in per_axis[1] for x in per_axis[2]]


def autocorrelation_length(block: np.ndarray) -> np.ndarray:
    """Lag (voxels) at which the block's normalised autocorrelation first falls to 1/e, per axis.

    Parameters
    ----------
    block : ndarray, shape (nz, ny, nx), any real dtype
        Grey levels; its own mean is removed.

    Returns
    -------
    ndarray, shape (3,), float64, voxels
        ``(z, y, x)``, interpolated linearly between lags; ``n / 2`` on an axis of ``n``
        voxels where it does not fall that far (a lower bound), NaN for a constant block.
        Unbiased: the sum of products at lag ``k`` is divided by the number of voxel pairs.
        Lag by lag, stopping at the crossing: a fine texture costs a few passes over the block.
    """
    v = np.asarray(block, dtype=np.float32)
    v = v - np.float32(v.mean(dtype=np.float64))
    var = float(np.mean(v.astype(np.float64) ** 2))
    out = np.full(3, math.nan)
    if not var > 0:
        return out
    buffer = np.empty_like(v)
    for axis in range(3):
        n = v.shape[axis]
        prev, out[axis] = 1.0, n / 2
        for lag in range(1, n // 2 + 1):
            ahead = tuple(slice(lag, None) if a == axis else slice(None) for a in range(3))
            behind = tuple(slice(None, n - lag) if a == axis else slice(None) for a in range(3))
            product = np.multiply(v[ahead], v[behind], out=buffer[behind])
            rho = float(product.sum(dtype=np.float64)) / product.size / var
            if rho < 1 / math.e:
                out[axis] = lag - 1 + (prev - 1 / math.e) / (prev - rho)
                break
            prev = rho
    return out


def texture_task(f_ref: ArrayRef, roi: tuple[slice, slice, slice]) -> float:
    """Task: the reference's autocorrelation length (voxels of its level), the median over
    the sampled blocks (:func:`sample_boxes`) and the three axes; NaN if every block is constant.

    A block's own mean is removed, so the median reads 10–25 % below the whole scan's
    value on a coarse texture (its longest wavelengths go with the block mean: 17.7 / 15.5
    voxels against 21 / 20 on the 4.5×-scaled grains / concrete, 128³) and within 2 % on a
    fine one; the median keeps a block of air at a corner of the ROI, whose edge would read
    as a long length, from setting it.
    """
    lengths = [autocorrelation_length(f_ref.read(box)) for box in sample_boxes(roi)]
    lengths = np.concatenate(lengths)
    lengths = lengths[np.isfinite(lengths)]
    return float(np.median(lengths)) if lengths.size else math.nan


def measure_texture(runner, f_ref: ArrayRef, mesh: Mesh, level: int, progress=None) -> float:
    """The reference's autocorrelation length on the correlated ``level`` (voxels of it), by
    one :func:`texture_task` on ``runner`` over ``mesh``'s ROI; reported by a ``texture``
    event with the length that level starts with (:func:`start_length`)."""
    length = next(iter(runner.map_unordered(texture_task, [(f_ref, mesh.roi)])))
    emit(progress, stage="texture", level=level, length=length,
         start_length=start_length(mesh.element_size, length), element_size=mesh.element_size)
    return length


def start_length(element_size: float, texture_length: float) -> float:
    """The regularisation length a level starts with, voxels of the level.

    Parameters
    ----------
    element_size : float
        ``ℓ``, voxels of the level.
    texture_length : float
        The reference's autocorrelation length ``A`` on that level (:func:`texture_task`),
        voxels; NaN: unknown.

    Returns
    -------
    float
        ``START_LENGTH ℓ max(1, A / max(ℓ, FINE_TEXTURE))²`` rounded (geometrically) to the
        nearest candidate length of the automatic choice, at most the longest.

    Examples
    --------
    >>> start_length(8, 6.0), start_length(4, 6.0), start_length(8, 11.5), start_length(8, 20.0)
    (16.0, 8.0, 32.0, 90.50966799187809)
    """
    ell = float(element_size)
    ratio = texture_length / max(ell, FINE_TEXTURE) if math.isfinite(texture_length) else 1.0
    wanted = START_LENGTH * max(1.0, ratio) ** 2
    grid = np.array([START_LENGTH * c for c in CANDIDATES if START_LENGTH * c <= CANDIDATES[-1]])
    return float(grid[np.argmin(np.abs(np.log(grid / wanted)))] * ell)
