"""C8 mesh: regular 8-node cubic elements, shape-function table, blocks, level transfer.

Conventions (shared/DESIGN.md, docs/architecture.md): element ``k`` along an axis covers
voxels ``origin + k*ell … origin + (k+1)*ell - 1``; node ``k`` sits at
``origin + k*ell - 0.5`` so that every voxel belongs to exactly one element and the
integrals of the paper (section 3, eq. for ``M`` and ``b``) are exact sums over voxels.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

#: offsets (dz, dy, dx) of the 8 local nodes, local index ``a = 4*dz + 2*dy + dx``
LOCAL_NODES = np.array([(a >> 2 & 1, a >> 1 & 1, a & 1) for a in range(8)], dtype=np.int64)
#: node offsets (dz, dy, dx) of the 27-point stencil entries ``k`` (docs/architecture.md):
#: ``(k // 9 - 1, (k // 3) % 3 - 1, k % 3 - 1)``, so ``STENCIL_OFFSETS[26 - k] == -STENCIL_OFFSETS[k]``
STENCIL_OFFSETS = np.array([(k // 9 - 1, (k // 3) % 3 - 1, k % 3 - 1) for k in range(27)], dtype=np.int64)


@functools.lru_cache(maxsize=32)
def shape_table(ell: int) -> np.ndarray:
    """Trilinear shape functions at the voxel centres of one element.

    Parameters
    ----------
    ell : int
        Element edge, voxels.

    Returns
    -------
    N : ndarray, shape (ell, ell, ell, 8), float64
        ``N[lz, ly, lx, a]`` for local node ``a = 4*dz + 2*dy + dx``. The local coordinate
        of voxel ``l`` is ``xi = (l + 0.5) / ell``; rows sum to 1. Read-only (cached).
    """
    xi = (np.arange(ell) + 0.5) / ell
    one_d = np.stack([1.0 - xi, xi])  # (2, ell): [d, l]
    table = np.empty((ell, ell, ell, 8))
    for a, (dz, dy, dx) in enumerate(LOCAL_NODES):
        table[..., a] = (
            one_d[dz][:, None, None] * one_d[dy][None, :, None] * one_d[dx][None, None, :]
        )
    table.setflags(write=False)
    return table


@dataclass(frozen=True)
class Block:
    """A box of whole elements: the work unit of one task.

    ``elements[i]`` is the element range ``(e0, e1)`` along axis ``i``; the block owns
    voxels ``origin + e0*ell … origin + e1*ell - 1`` and nodes ``e0 … e1`` (inclusive).
    """

    elements: tuple[tuple[int, int], tuple[int, int], tuple[int, int]]

    @property
    def node_slices(self) -> tuple[slice, slice, slice]:
        return tuple(slice(e0, e1 + 1) for e0, e1 in self.elements)

    @property
    def n_elements(self) -> tuple[int, int, int]:
        return tuple(e1 - e0 for e0, e1 in self.elements)


@dataclass(frozen=True)
class Mesh:
    """Regular C8 mesh over a box ROI of whole elements (one pyramid level).

    Parameters
    ----------
    origin : tuple of 3 int
        First ROI voxel ``(z, y, x)``, voxels of the level.
    element_size : int
        Element edge ``ell``, voxels of the level.
    shape : tuple of 3 int
        Number of elements per axis.
    """

    origin: tuple[int, int, int]
    element_size: int
    shape: tuple[int, int, int]

    @property
    def nodes_shape(self) -> tuple[int, int, int]:
        return tuple(n + 1 for n in self.shape)

    @property
    def roi(self) -> tuple[slice, slice, slice]:
        """The voxels the mesh covers, as slices of the level array."""
        ell = self.element_size
        return tuple(slice(o, o + n * ell) for o, n in zip(self.origin, self.shape))

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape)) * self.element_size**3

    def node_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Node coordinates along each axis, ``origin + k*ell - 0.5`` (float64, voxels)."""
        ell = self.element_size
        return tuple(o + ell * np.arange(n + 1) - 0.5 for o, n in zip(self.origin, self.shape))

    def element_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Element-centre coordinates along each axis, ``origin + (k + 1/2) ell - 0.5`` (float64, voxels)."""
        return tuple((nodes[1:] + nodes[:-1]) / 2 for nodes in self.node_axes())

    def node_coords(self) -> np.ndarray:
        """Node positions, shape ``(3, nz+1, ny+1, nx+1)``, float64, voxels of the level."""
        return np.stack(np.meshgrid(*self.node_axes(), indexing="ij"))

    def blocks(self, elements_per_block: int) -> list[Block]:
        """Cut the mesh into blocks of at most ``elements_per_block`` elements per side."""
        m = max(1, int(elements_per_block))
        ranges = [
            [(e0, min(e0 + m, n)) for e0 in range(0, n, m)] for n in self.shape
        ]
        return [Block((rz, ry, rx)) for rz in ranges[0] for ry in ranges[1] for rx in ranges[2]]

    def block_core(self, block: Block) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """Absolute first voxel and shape of a block's core (voxels of the level)."""
        ell = self.element_size
        start = tuple(o + e0 * ell for o, (e0, _) in zip(self.origin, block.elements))
        shape = tuple((e1 - e0) * ell for e0, e1 in block.elements)
        return start, shape

    def evaluate(self, u: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Evaluate the C8 field at arbitrary points (trilinear, extrapolated outside).

        Parameters
        ----------
        u : ndarray, shape (3, nz+1, ny+1, nx+1), float64, voxels
            Nodal displacement.
        points : ndarray, shape (3, ...), float64
            Positions, voxels of this level.

        Returns
        -------
        ndarray, shape (3, ...), float64
            Field values. Points outside the mesh take the linear extension of the
            nearest element, which is what a level transfer needs at the rim.
        """
        idx, frac = zip(*(self.element_index(axis, points[axis]) for axis in range(3)))
        out = np.zeros((3,) + points.shape[1:])
        for dz, dy, dx in LOCAL_NODES:
            w = (
                (frac[0] if dz else 1 - frac[0])
                * (frac[1] if dy else 1 - frac[1])
                * (frac[2] if dx else 1 - frac[2])
            )
            out += w * u[:, idx[0] + dz, idx[1] + dy, idx[2] + dx]
        return out

    def element_index(self, axis: int, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Element index along ``axis`` of ``positions`` and their local coordinate in it.

        Parameters
        ----------
        axis : int
            0, 1, 2 for ``z, y, x``.
        positions : ndarray, any shape, float64, voxels of this level

        Returns
        -------
        k : ndarray, shape of ``positions``, int64
            Element index, clipped to ``0 … shape[axis] - 1`` (outside points take the
            nearest element, as in :meth:`evaluate`).
        frac : ndarray, shape of ``positions``, float64
            ``(position - node k) / ell`` (in ``[0, 1]`` inside the mesh).
        """
        t = (np.asarray(positions, np.float64) - (self.origin[axis] - 0.5)) / self.element_size
        k = np.clip(np.floor(t), 0, self.shape[axis] - 1).astype(np.int64)
        return k, t - k

    def evaluate_grid(self, u: np.ndarray, axes) -> np.ndarray:
        """Evaluate the C8 field on the grid ``axes[0] × axes[1] × axes[2]`` (separably).

        Same values as :meth:`evaluate` on the meshgrid of ``axes``, but the trilinear
        interpolation is done one axis at a time (x, then y, then z), so the cost is that
        of three 1-D interpolations and no index array of the grid's size is built.

        Parameters
        ----------
        u : ndarray, shape (3, nz+1, ny+1, nx+1), float64, voxels
            Nodal displacement.
        axes : sequence of 3 ndarray, shapes (gz,), (gy,), (gx,), float64
            Grid positions along ``z, y, x``, voxels of this level.

        Returns
        -------
        ndarray, shape (3, gz, gy, gx), float64
        """
        out = np.asarray(u, np.float64)
        for axis in (2, 1, 0):
            k, frac = self.element_index(axis, axes[axis])
            shape = [1] * 4
            shape[axis + 1] = -1
            frac = frac.reshape(shape)
            out = (np.take(out, k, axis=axis + 1) * (1.0 - frac)
                   + np.take(out, k + 1, axis=axis + 1) * frac)
        return out


def node_colours(nodes_shape, period: int):
    """Boolean masks (nodes_shape) of the nodes ``period`` apart on every axis, one per colour
    (empty colours left out): unit vectors on one colour probe an operator that couples nodes
    at most ``(period - 1) / 2`` apart without their columns overlapping."""
    grid = np.indices(tuple(nodes_shape))
    for colour in np.ndindex(*(min(period, int(n)) for n in nodes_shape)):
        yield np.all([grid[d] % period == colour[d] for d in range(3)], axis=0)


def level0_position(coords, scale: float):
    """Level-0 coordinates of positions ``coords`` on a level ``scale = 2^s`` times coarser.

    A voxel ``j`` of level ``s`` has its centre at level-0 coordinate ``2^s j + (2^s - 1) / 2``
    (shared/DESIGN.md): the one place this offset is written. Physical positions are this
    times the level-0 voxel size.
    """
    return scale * np.asarray(coords, dtype=np.float64) + (scale - 1) / 2


def level_to_level(coords: np.ndarray, from_level: int, to_level: int) -> np.ndarray:
    """Convert positions between pyramid levels (:func:`level0_position` both ways)."""
    s1 = 2.0**to_level
    return (level0_position(coords, 2.0**from_level) - (s1 - 1) / 2) / s1


def carry_field(u: np.ndarray, source: Mesh, source_level: int, points: np.ndarray, level: int, *,
                clamp: bool = False) -> np.ndarray:
    """The C8 field ``u`` of ``source`` at ``points`` of another level or mesh: the one way
    chunkdic carries a nodal field onto other nodes (level transfer, start fields, composed
    increments).

    Positions are converted between levels with the half-voxel offset and the values
    scaled by ``2^(source_level - level)``, because displacements are in voxels of their
    level (paper section 3, multiscale).

    Parameters
    ----------
    u : ndarray, shape (3, nz+1, ny+1, nx+1), float64, voxels of ``source_level``
        Nodal field of ``source`` (no NaN: see :func:`chunkdic.method.start.filled`).
    source : Mesh
    source_level : int
    points : ndarray, shape (3, ...), float64, voxels of ``level``
    level : int
    clamp : bool, keyword-only
        Where ``points`` leave the source mesh: False, the linear extension of the nearest
        element however far (:meth:`Mesh.evaluate`; a level transfer, whose points lie
        within one element of the mesh); True, that extension up to one element beyond
        the mesh's outer nodes and the value at that limit further out (positions clamped:
        a start field that kept growing far from the data would only mislead).

    Returns
    -------
    ndarray, shape (3, ...), float64, voxels of ``level``
    """
    at = level_to_level(points, level, source_level)
    if clamp:
        ell = source.element_size
        at = np.stack([np.clip(at[axis], nodes[0] - ell, nodes[-1] + ell)
                       for axis, nodes in enumerate(source.node_axes())])
    return source.evaluate(u, at) * 2.0 ** (source_level - level)


def transfer(u: np.ndarray, coarse: Mesh, coarse_level: int, fine: Mesh, fine_level: int) -> np.ndarray:
    """Carry a nodal field from a coarse level's mesh to a finer level's mesh: the coarse
    field at the fine nodes (:func:`carry_field`, not clamped)."""
    return carry_field(u, coarse, coarse_level, fine.node_coords(), fine_level)
