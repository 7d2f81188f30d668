"""Elements cut by a known crack surface: which side each voxel is on, and their sums.

A crack given as a label image (non-zero voxels: the surface, docs/cracks.md, "Correlating
with a known crack") splits the support of a node — its ``(2ℓ)³`` box of elements, clipped
to the mesh — into pieces: the connected components (6-connectivity) of the voxels off the
surface. A node whose support falls into two or more pieces is *split*: the piece it lies
in keeps the node's own value ``u`` (copy 0), the others share its second copy ``u'``
(copy 1, the other side); a support merely touched by the
surface (near a crack tip, the material joined around it) keeps one copy. Each voxel of an
element with a split node takes, for each of the element's nodes, the copy of the piece it
lies in (:func:`cut_block`); the surface's own voxels belong to neither side and are left
out of those elements' sums. This is the phantom-node form of an element split by a
discontinuity (Hansbo & Hansbo 2004), read off the voxels.

The numba kernels sum the other elements as they are; the elements with a split node
(:attr:`CutBlock.elements`) go through the plain NumPy sums here, shared by the block
tasks (:mod:`chunkdic.passes.tasks`) and the dense twin (:mod:`chunkdic.passes.dense`):
:func:`cut_b_sums` fills their :class:`~chunkdic.kernels.blocks.ElementSums` (copy 0) and
returns the sums of the copies 1, and :func:`cut_m_sums` gives their ``M`` (paper section 3,
``M_ij`` with each voxel's own shape functions): the couplings of copies 0 into the block's
stencil, the others as node-pair entries.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.ndimage as ndi

from ..kernels.blocks import gradient_block, voxel_xi
from ..kernels.twins import taper
from ..mesh import LOCAL_NODES, STENCIL_OFFSETS, shape_table

#: a node gets a second copy when the other side's piece of its support carries at least this
#: share of its weight (``Σ N²`` over the piece's usable voxels, against the whole support): a
#: thinner sliver (the surface near the support's far face) determines a copy too poorly to
#: measure it (modified Gauss–Newton crawled at 0.7 % and 0.07 % on the 64³ test pair), and
#: its voxels are left out instead, the node keeping one copy, its penalty still released
MIN_PIECE = 0.01

__all__ = ["MIN_PIECE", "CrackLabels", "CutBlock", "cut_block", "cut_b_sums", "cut_m_sums", "read_cut"]


@dataclasses.dataclass(frozen=True)
class CrackLabels:
    """The crack surface at one level, as the tasks read it.

    Attributes
    ----------
    labels : object with ``read(region)`` and ``shape``
        The level's crack voxels (non-zero: the surface; an :class:`~chunkdic.io.handles.ArrayRef`
        of the binarised labels' sum level, or an in-memory array for the dense twin).
    origin : tuple of 3 int
        The mesh's first voxel, voxels of the level.
    elements : tuple of 3 int
        The mesh's elements per axis.
    band : int
        Voxels within this distance (Chebyshev) of the surface are left out of the cut
        elements' sums: there the low-pass of ``g`` mixes the two sides' textures across the
        opened crack (``face_margin`` of the low-pass, :func:`chunkdic.passes.prefilter.face_margin`).
    """

    labels: object
    origin: tuple
    elements: tuple
    band: int = 0


@dataclasses.dataclass
class CutBlock:
    """The elements of one block that have a split node, and each voxel's side.

    Attributes
    ----------
    released : ndarray, shape (ez+1, ey+1, ex+1), bool
        The block's nodes whose support the surface splits (their penalty terms released).
    split : ndarray, shape (ez+1, ey+1, ex+1), bool
        Those of them with a second copy (the other side's piece carries at least
        :data:`MIN_PIECE` of the node's weight).
    edges : ndarray, shape (3, ez+1, ey+1, ex+1), bool
        ``edges[t, n]``: the surface meets the mesh edge from node ``n`` to ``n + e_t`` (the
        ``2×2`` voxel columns along it hold a surface voxel; False past the block's elements).
    elements : ndarray, shape (n, 3), int
        The block's elements with a released node (indices in the block).
    copies : ndarray, shape (n, ell, ell, ell, 8), uint8
        Per voxel of those elements, the copy (0 or 1) of each local node it uses.
    surface : ndarray, shape (n, ell, ell, ell), bool
        Their voxels on the surface or within :attr:`CrackLabels.band` of it (left out of the sums).
    """

    released: np.ndarray
    split: np.ndarray
    edges: np.ndarray
    elements: np.ndarray
    copies: np.ndarray
    surface: np.ndarray

    @property
    def empty(self) -> bool:
        return len(self.elements) == 0


def read_cut(crack: CrackLabels | None, block_elements, ell: int) -> CutBlock | None:
    """The :class:`CutBlock` of a block (element ranges ``block_elements``, global), from the
    crack voxels of its elements and of one ring of elements around it (the supports of its
    nodes); None without a crack or when the block has no split node."""
    if crack is None:
        return None
    lo = [max(e0 - 1, 0) for e0, _ in block_elements]
    hi = [min(e1 + 1, n) for (_, e1), n in zip(block_elements, crack.elements)]
    region = tuple(slice(o + a * ell, o + b * ell) for o, a, b in zip(crack.origin, lo, hi))
    voxels = np.asarray(crack.labels.read(region)) != 0
    if not voxels.any():
        return None
    cut = cut_block(voxels, lo, block_elements, crack.elements, ell, crack.band)
    return None if cut.empty else cut


def cut_block(voxels: np.ndarray, first, block_elements, mesh_elements, ell: int, band: int = 0) -> CutBlock:
    """Split nodes and voxel sides of a block (module docstring).

    Parameters
    ----------
    voxels : ndarray, bool
        Crack voxels over the elements ``first[i] …`` of the mesh along each axis, covering
        the block's elements and one ring around them (clipped to the mesh).
    first : tuple of 3 int
        The first element ``voxels`` covers.
    block_elements : tuple of 3 (e0, e1)
        The block's element ranges (global).
    mesh_elements : tuple of 3 int
    ell : int
    band : int
        :attr:`CrackLabels.band`.
    """
    n0 = [e0 for e0, _ in block_elements]
    nodes_shape = tuple(e1 - e0 + 1 for e0, e1 in block_elements)
    left_out = ndi.binary_dilation(voxels, np.ones((3, 3, 3), bool), iterations=band) if band > 0 else voxels
    released, split = np.zeros(nodes_shape, bool), np.zeros(nodes_shape, bool)
    pieces = {}
    for local in np.ndindex(*nodes_shape):
        node = [n + k for n, k in zip(n0, local)]
        lo = [max(n - 1, 0) for n in node]
        hi = [min(n + 1, m) for n, m in zip(node, mesh_elements)]
        box = tuple(slice((a - f) * ell, (b - f) * ell) for a, b, f in zip(lo, hi, first))
        surface = voxels[box]
        if not surface.any():
            continue
        other = _other_side(surface, [(n - a) * ell for n, a in zip(node, lo)])
        if other is None:
            continue
        released[local] = True
        weight = _support_weight(node, lo, surface.shape, ell)
        usable = other.astype(bool) & ~left_out[box]
        has_copy = weight[usable].sum() >= MIN_PIECE * weight.sum()
        split[local] = has_copy
        pieces[local] = (lo, other, has_copy)
    elements, copies, surfaces = [], [], []
    e_shape = tuple(e1 - e0 for e0, e1 in block_elements)
    for e in np.ndindex(*e_shape):
        nodes = [tuple(int(v) for v in np.add(e, d)) for d in LOCAL_NODES]
        if not any(released[n] for n in nodes):
            continue
        at = [(n0[i] + e[i] - first[i]) * ell for i in range(3)]
        out = left_out[at[0]:at[0] + ell, at[1]:at[1] + ell, at[2]:at[2] + ell].copy()
        c = np.zeros((ell, ell, ell, 8), np.uint8)
        for a, n in enumerate(nodes):
            if n in pieces:
                lo, other, has_copy = pieces[n]
                o = [(n0[i] + e[i] - lo[i]) * ell for i in range(3)]
                piece = other[o[0]:o[0] + ell, o[1]:o[1] + ell, o[2]:o[2] + ell]
                if has_copy:
                    c[..., a] = piece
                else:  # a sliver the node cannot be measured on: its voxels left out
                    out |= piece.astype(bool)
        elements.append(e)
        copies.append(c)
        surfaces.append(out)
    n = len(elements)
    return CutBlock(released, split, _cut_edges(voxels, first, block_elements, ell), np.array(elements, int).reshape(n, 3),
                    np.array(copies, np.uint8).reshape((n, ell, ell, ell, 8)),
                    np.array(surfaces, bool).reshape((n, ell, ell, ell)))


def _cut_edges(voxels: np.ndarray, first, block_elements, ell: int) -> np.ndarray:
    """:attr:`CutBlock.edges` of a block from its crack voxels (as :func:`cut_block` gets them)."""
    n0 = [e0 for e0, _ in block_elements]
    nodes_shape = tuple(e1 - e0 + 1 for e0, e1 in block_elements)
    edges = np.zeros((3,) + nodes_shape, bool)
    for t in range(3):
        for local in np.ndindex(*nodes_shape):
            if local[t] == nodes_shape[t] - 1:
                continue
            box = []
            for i in range(3):
                at = (n0[i] + local[i] - first[i]) * ell
                box.append(slice(at, at + ell) if i == t else slice(max(at - 1, 0), at + 1))
            edges[(t, *local)] = bool(voxels[tuple(box)].any())
    return edges


def _support_weight(node, lo, shape, ell: int) -> np.ndarray:
    """``N²`` of ``node``'s shape function over its support box (starting at element ``lo``, of ``shape`` voxels)."""
    axes = []
    for n, a, m in zip(node, lo, shape):
        i = np.arange(m)
        axes.append(np.clip(1.0 - np.abs(i + 0.5 - (n - a) * ell) / ell, 0.0, 1.0) ** 2)
    return axes[0][:, None, None] * axes[1][None, :, None] * axes[2][None, None, :]


def _other_side(surface: np.ndarray, corner) -> np.ndarray | None:
    """The voxels of a node's support off the node's own piece (uint8), None when the surface
    leaves the support in one piece. The node's piece is the one most of the 2×2×2 voxels
    around it (``corner``: the node's position's voxel index in the support box, its upper
    neighbours) lie in; the largest piece when the surface covers them all."""
    labels, count = ndi.label(~surface)
    if count < 2:
        return None
    around = labels[tuple(slice(max(c - 1, 0), c + 1) for c in corner)]
    votes = np.bincount(around.ravel(), minlength=count + 1)[1:]
    main = int(np.argmax(votes if votes.any() else np.bincount(labels.ravel())[1:])) + 1
    return ((labels != main) & (labels > 0)).astype(np.uint8)


def _element_fields(cut: CutBlock, k: int, u_block: np.ndarray, other_block: np.ndarray, ell: int) -> np.ndarray:
    """The displacement (3, ell³) at the voxels of cut element ``k``, each with its copies."""
    e = cut.elements[k]
    nodes = tuple(np.add(e, LOCAL_NODES).T)
    u0 = u_block[(slice(None), *nodes)]  # (3, 8)
    u1 = other_block[(slice(None), *nodes)]
    c = cut.copies[k].reshape(-1, 8).astype(bool)  # (V, 8)
    N = shape_table(ell).reshape(-1, 8)
    return np.einsum("va,iva->iv", N, np.where(c[None], u1[:, None, :], u0[:, None, :]))


def _voxel_positions(cut: CutBlock, k: int, core_origin, ell: int) -> np.ndarray:
    """Level coordinates (3, ell³) of the voxels of cut element ``k``."""
    grid = np.meshgrid(*[np.arange(ell)] * 3, indexing="ij")
    return np.stack([core_origin[i] + cut.elements[k][i] * ell + grid[i].ravel() for i in range(3)]).astype(float)


def cut_b_sums(sums, cut: CutBlock, f: np.ndarray, lo, hi, ell: int, u_block: np.ndarray, other_block: np.ndarray,
               core_origin, g: np.ndarray, g_origin, g_shape, *, interpolation: str, center: float, margin: int,
               active: np.ndarray | None = None) -> np.ndarray:
    """Fill ``sums`` (:class:`~chunkdic.kernels.blocks.ElementSums` of the block, whose cut
    elements the numba kernel left out) with the cut elements' sums over their copies 0, and
    return the sums of their copies 1: ``(ez, ey, ex, 6, 8, 3)``, zero off the cut elements.

    ``u_block``, ``other_block``: the copies 0 and 1 of the block's nodes (3, ez+1, ey+1,
    ex+1), voxels (``other_block`` equals ``u_block`` at nodes not split); ``g`` the prepared
    window at ``g_origin`` covering both; the other parameters as :func:`chunkdic.kernels.b.b_sums`.
    """
    B1 = np.zeros_like(sums.B)
    grad = gradient_block(np.asarray(f, np.float32), lo, hi).astype(np.float64)
    fcore = np.asarray(f, np.float32)[lo[0]:f.shape[0] - hi[0], lo[1]:f.shape[1] - hi[1], lo[2]:f.shape[2] - hi[2]]
    N = shape_table(ell).reshape(-1, 8)
    q = voxel_xi(ell) - 0.5
    qs = [a.ravel() for a in np.meshgrid(q, q, q, indexing="ij")]
    for k, e in enumerate(cut.elements):
        if active is not None and active[tuple(e)] == 0:
            continue
        sl = tuple(slice(i * ell, (i + 1) * ell) for i in e)
        pos = _voxel_positions(cut, k, core_origin, ell) + _element_fields(cut, k, u_block, other_block, ell)
        surface = cut.surface[k].ravel()
        w = taper(pos, g_shape, margin)
        w[surface] = 0.0
        gv = np.zeros(w.size)
        on = w > 0
        if on.any():
            local = pos[:, on] - np.asarray(g_origin, float)[:, None]
            order, mode = (3, "mirror") if interpolation == "cubic" else (1, "nearest")
            gv[on] = ndi.map_coordinates(g, local, order=order, mode=mode, prefilter=False, output=np.float64)
        d = np.where(on, fcore[sl].ravel().astype(np.float64) - gv, 0.0)
        gp = np.where(on, gv - center, 0.0)
        v = np.stack([d, gp, np.ones(w.size), *qs])  # (6, V)
        G = grad[(slice(None),) + sl].reshape(3, -1) * w  # (3, V)
        c1 = cut.copies[k].reshape(-1, 8).astype(np.float64)
        sums.B[tuple(e)] = np.einsum("va,iv,qv->qai", N * (1.0 - c1), G, v)
        B1[tuple(e)] = np.einsum("va,iv,qv->qai", N * c1, G, v)
        sums.gram[tuple(e)] = (v * w) @ v.T
        sums.n_excluded += int(np.sum(~on & ~surface))
    return B1


def cut_m_sums(cut: CutBlock, f: np.ndarray, lo, hi, ell: int, u_block: np.ndarray, core_origin, g_shape, *,
               margin: int, active: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """``M`` of a block's cut elements at the field ``u_block`` (both copies equal, as when
    ``M`` is built): the couplings of copies 0, a 27-point stencil over the block's nodes
    (ez+1, ey+1, ex+1, 27, 3, 3), float64; and the couplings involving a copy 1, as a dict
    ``(node a, copy, node b, copy) -> 3×3`` with node triples in the block (copy 1 on one side at least).

    Voxels the field maps outside ``g`` and the surface's voxels are left out; no brightness
    condensation (``M`` only steers the iterations: their fixed point is ``b = λ R a``).
    """
    nodes_shape = u_block.shape[1:]
    stencil = np.zeros(tuple(nodes_shape) + (27, 3, 3))
    pairs: dict = {}
    grad = gradient_block(np.asarray(f, np.float32), lo, hi).astype(np.float64)
    N = shape_table(ell).reshape(-1, 8)
    for k, e in enumerate(cut.elements):
        if active is not None and active[tuple(e)] == 0:
            continue
        sl = tuple(slice(i * ell, (i + 1) * ell) for i in e)
        pos = _voxel_positions(cut, k, core_origin, ell) + _element_fields(cut, k, u_block, u_block, ell)
        w = taper(pos, g_shape, margin)
        w[cut.surface[k].ravel()] = 0.0
        G = grad[(slice(None),) + sl].reshape(3, -1)
        c1 = cut.copies[k].reshape(-1, 8).astype(np.float64)
        Ns = (N * (1.0 - c1), N * c1)
        for ca in (0, 1):
            for cb in (0, 1):
                Ke = np.einsum("v,va,vb,iv,jv->abij", w, Ns[ca], Ns[cb], G, G, optimize=True)
                for a, da in enumerate(LOCAL_NODES):
                    na = tuple(int(v) for v in np.add(e, da))
                    for b, db in enumerate(LOCAL_NODES):
                        if not Ke[a, b].any():
                            continue
                        if ca == 0 and cb == 0:
                            stencil[na + (_stencil_index(db - da),)] += Ke[a, b]
                        else:
                            key = (na, ca, tuple(int(v) for v in np.add(e, db)), cb)
                            pairs[key] = pairs.get(key, 0.0) + Ke[a, b]
    return stencil, pairs


def _stencil_index(offset) -> int:
    return int(np.flatnonzero((STENCIL_OFFSETS == np.asarray(offset)).all(axis=1))[0])


def fast_active(active: np.ndarray | None, cut: CutBlock | None, elements) -> np.ndarray | None:
    """The element activity the numba kernels sum (uint8, ``elements``): ``active`` (None:
    every element) without the cut elements, which :func:`cut_b_sums` / :func:`cut_m_sums` sum."""
    if cut is None:
        return active
    out = np.ones(tuple(elements), np.uint8) if active is None else np.array(active, np.uint8)
    out[tuple(cut.elements.T)] = 0
    return out


def global_pairs(pairs: dict, cut: CutBlock, first_node) -> tuple[dict, np.ndarray]:
    """:func:`cut_m_sums`' entries with the block's node triples made global (``first_node``:
    the block's first node), and the block's cut mesh edges (global, (n, 4): axis, node triple)."""
    shift = lambda n: tuple(int(a + b) for a, b in zip(n, first_node))  # noqa: E731
    edges = np.argwhere(cut.edges)
    edges[:, 1:] += np.asarray(first_node)
    return {(shift(a), ca, shift(b), cb): v for (a, ca, b, cb), v in pairs.items()}, edges


def other_rows(nodal: np.ndarray, cut: CutBlock, first_node) -> tuple[np.ndarray, np.ndarray]:
    """The reduced nodal rows of the copies 1 (:class:`chunkdic.method.brightness.Partials`'
    ``nodal``, (R, ez+1, ey+1, ex+1, 3)) at the block's split nodes: their global index
    triples (n, 3) and rows (R, n, 3)."""
    local = np.argwhere(cut.split)
    return local + np.asarray(first_node), nodal[(slice(None), *local.T)]
