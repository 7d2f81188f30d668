"""Galerkin coarse operators of the multigrid V-cycle, built on stencils (never assembled).

Hierarchy. C8 fields nest: a trilinear field on a grid of every other node is exactly a
trilinear field on the fine grid, so the prolongation ``P`` is trilinear interpolation of
nodal values (per axis: the coarse nodes are the even fine nodes plus the last one, so an
even axis ends with an interval of one fine step) and the restriction is ``Pᵀ``. Coarse
operators are Galerkin ``Pᵀ A P``, computed one axis at a time on stencils (never
assembled):

* ``M`` (27-point, a different block per node) stays 27-point, since a reach of one node
  shrinks to ``(1 + 2) // 2 = 1`` coarse node; kept per node, half-stored like the fine one.
* ``R`` (reach 2: 125-point for the equilibrium gap, 13 of them for Tikhonov) stays reach 2.
  It is the same at every node farther than a few nodes from the faces, so it is kept as a
  *class stencil*: one block row per combination of per-axis classes (the first
  :data:`CORE` positions, the interior, the last :data:`CORE`), at most 9³ rows whatever
  the mesh. The fine one is probed on a mesh of at most 7³ nodes (like
  :meth:`~chunkdic.solve.regularizer.Regularizer.diagonal_blocks`), the coarse ones follow
  by the same Galerkin product.

Memory: the coarse ``M`` are 1/8, 1/64, … of the fine one (float32), the ``R`` class
stencils a few MB; a level is built slab by slab along z (:func:`coarsened_in_slabs`), so
the intermediate after the first axis (half the fine size) is never whole.
"""


from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .regularizer import Regularizer

COARSEST = 216
#: positions per mesh end that a class stencil keeps apart from the interior: enough for
#: the reach-2 ``R`` and its Galerkin coarsenings (a coarse node ``I ≥ 4`` only sees fine
#: nodes ``≥ 2I - 3 ≥ 5``)
CORE = 4
#: classes of the fine ``R``: its rows differ from the interior's up to 2 nodes from a face
FINE_CORE = 3
#: coarse z planes of ``M`` built together (:func:`coarsened_in_slabs`)
SLAB = 16



# --- transfer between levels ---------------------------------------------------------

def coarse_size(n: int) -> int:
    """Nodes of the coarse axis of a fine axis of ``n`` nodes (no coarsening below 3)."""
    return n // 2 + 1 if n >= 3 else n


def axis_transfer(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 1-D prolongation of an axis of ``n`` fine nodes, both ways.

    The coarse nodes sit at fine positions ``0, 2, 4, …`` and ``n - 1``; a fine node
    between two of them takes the linear interpolation of their values.

    Returns
    -------
    fine_index, fine_weight : ndarray, shape (n, 2), int64 / float64
        The (at most) two coarse nodes of each fine node and their weights.
    support, support_weight : ndarray, shape (nc, 3), int64 / float64
        The (at most) three fine nodes of each coarse node's hat and their weights; -1 pads.
    """
    nc = coarse_size(n)
    pos = np.minimum(2 * np.arange(nc), n - 1) if nc < n else np.arange(n)
    fine_index = np.zeros((n, 2), np.int64)
    fine_weight = np.zeros((n, 2))
    support = np.full((nc, 3), -1, np.int64)
    support_weight = np.zeros((nc, 3))
    fill = np.zeros(nc, np.int64)
    for i in range(n):
        c = int(np.searchsorted(pos, i, side="right")) - 1
        if pos[c] == i:
            entries = [(c, 1.0)]
        else:
            t = (i - pos[c]) / (pos[c + 1] - pos[c])
            entries = [(c, 1.0 - t), (c + 1, t)]
        for k, (cc, w) in enumerate(entries):
            fine_index[i, k], fine_weight[i, k] = cc, w
            support[cc, fill[cc]], support_weight[cc, fill[cc]] = i, w
            fill[cc] += 1
    return fine_index, fine_weight, support, support_weight


@numba.njit(nogil=True, cache=True)
def transfer(fine, iz, wz, iy, wy, ix, wx, coarse, restrict):
    """Trilinear transfer between a fine nodal field and a coarse one, both (…, 3).

    ``restrict`` False: ``fine += P coarse`` (prolongation: trilinear interpolation of the
    coarse nodal values); True: ``coarse = Pᵀ fine`` (restriction, its transpose). One loop
    for both, so the two stay transposes of each other.
    """
    if restrict:
        coarse[:] = 0.0
    nz, ny, nx = fine.shape[0], fine.shape[1], fine.shape[2]
    for z in range(nz):
        for y in range(ny):
            for xx in range(nx):
                for a in range(2):
                    fa = wz[z, a]
                    if fa == 0.0:
                        continue
                    for b in range(2):
                        fb = fa * wy[y, b]
                        if fb == 0.0:
                            continue
                        for c in range(2):
                            f = fb * wx[xx, c]
                            if f == 0.0:
                                continue
                            i, j, k = iz[z, a], iy[y, b], ix[xx, c]
                            for q in range(3):
                                if restrict:
                                    coarse[i, j, k, q] += f * fine[z, y, xx, q]
                                else:
                                    fine[z, y, xx, q] += f * coarse[i, j, k, q]


# --- class stencils ------------------------------------------------------------------

def class_map(n: int, core: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis classes of a class stencil: ``(cls, reps)``.

    ``cls`` (n,) gives each position's class; ``reps`` (classes,) one position of each.
    The first ``core`` and last ``core`` positions are classes of their own, the rest one
    interior class; an axis of at most ``2 core + 1`` nodes has one class per node.
    """
    if n <= 2 * core + 1:
        return np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64)
    cls = np.full(n, core, np.int64)
    cls[:core] = np.arange(core)
    cls[n - core:] = np.arange(core + 1, 2 * core + 1)
    reps = np.concatenate([np.arange(core), [core], np.arange(n - core, n)]).astype(np.int64)
    return cls, reps


@numba.njit(nogil=True, cache=True)
def _class_matvec(S, cz, cy, cx, reach, nonzero_ptr, nonzero, diagonal, lam, x, y):
    """``y += λ A x``, ``A`` the half-stored class stencil ``S`` (Kz, Ky, Kx, h, 3, 3) of reach ``reach``.

    ``S[cz[z], cy[y], cx[x], h]`` is the block of node (z, y, x) towards the ``h``-th offset
    of the upper half (lexicographic ``(dz, dy, dx) ≥ 0`` of the ``(2 reach + 1)³`` box);
    the lower half is the transpose of the neighbour's. Only the offsets
    ``nonzero[nonzero_ptr[K] : nonzero_ptr[K + 1]]`` of class ``K = (a Ky + b) Kx + c`` are
    visited, and with ``diagonal`` only the blocks' diagonals (Tikhonov acts per component:
    41 of 63 offsets, 3 of 9 entries).
    """
    w = 2 * reach + 1
    kc = (w * w * w - 1) // 2
    oz = np.empty(kc + 1, np.int64)
    oy = np.empty(kc + 1, np.int64)
    ox = np.empty(kc + 1, np.int64)
    for h in range(kc + 1):
        k = h + kc
        oz[h], oy[h], ox[h] = k // (w * w) - reach, (k // w) % w - reach, k % w - reach
    Ky, Kx = S.shape[1], S.shape[2]
    nz, ny, nx = x.shape[0], x.shape[1], x.shape[2]
    for z in range(nz):
        for yy in range(ny):
            for xx in range(nx):
                c0, c1, c2 = x[z, yy, xx, 0], x[z, yy, xx, 1], x[z, yy, xx, 2]
                a, b, c = cz[z], cy[yy], cx[xx]
                K = (a * Ky + b) * Kx + c
                for t in range(nonzero_ptr[K], nonzero_ptr[K + 1]):
                    h = nonzero[t]
                    z2, y2, x2 = z + oz[h], yy + oy[h], xx + ox[h]
                    if z2 < 0 or z2 >= nz or y2 < 0 or y2 >= ny or x2 < 0 or x2 >= nx:
                        continue
                    s = S[a, b, c, h]
                    v0, v1, v2 = x[z2, y2, x2, 0], x[z2, y2, x2, 1], x[z2, y2, x2, 2]
                    if diagonal:
                        s0, s1, s2 = lam * s[0, 0], lam * s[1, 1], lam * s[2, 2]
                        y[z, yy, xx, 0] += s0 * v0
                        y[z, yy, xx, 1] += s1 * v1
                        y[z, yy, xx, 2] += s2 * v2
                        if h > 0:
                            y[z2, y2, x2, 0] += s0 * c0
                            y[z2, y2, x2, 1] += s1 * c1
                            y[z2, y2, x2, 2] += s2 * c2
                        continue
                    y[z, yy, xx, 0] += lam * (s[0, 0] * v0 + s[0, 1] * v1 + s[0, 2] * v2)
                    y[z, yy, xx, 1] += lam * (s[1, 0] * v0 + s[1, 1] * v1 + s[1, 2] * v2)
                    y[z, yy, xx, 2] += lam * (s[2, 0] * v0 + s[2, 1] * v1 + s[2, 2] * v2)
                    if h > 0:
                        y[z2, y2, x2, 0] += lam * (s[0, 0] * c0 + s[1, 0] * c1 + s[2, 0] * c2)
                        y[z2, y2, x2, 1] += lam * (s[0, 1] * c0 + s[1, 1] * c1 + s[2, 1] * c2)
                        y[z2, y2, x2, 2] += lam * (s[0, 2] * c0 + s[1, 2] * c1 + s[2, 2] * c2)


@numba.njit(nogil=True, cache=True)
def assemble_dense(S, cz, cy, cx, reach, lam, A):
    """``A += λ`` the dense matrix (3N, 3N) of the half-stored class stencil ``S`` (coarsest level)."""
    w = 2 * reach + 1
    kc = (w * w * w - 1) // 2
    nz, ny, nx = len(cz), len(cy), len(cx)
    for z in range(nz):
        for yy in range(ny):
            for xx in range(nx):
                n = (z * ny + yy) * nx + xx
                for h in range(kc + 1):
                    k = h + kc
                    z2 = z + k // (w * w) - reach
                    y2 = yy + (k // w) % w - reach
                    x2 = xx + k % w - reach
                    if z2 < 0 or z2 >= nz or y2 < 0 or y2 >= ny or x2 < 0 or x2 >= nx:
                        continue
                    m = (z2 * ny + y2) * nx + x2
                    s = S[cz[z], cy[yy], cx[xx], h]
                    for i in range(3):
                        for j in range(3):
                            A[3 * n + i, 3 * m + j] += lam * s[i, j]
                            if h > 0:
                                A[3 * m + j, 3 * n + i] += lam * s[i, j]


@numba.njit(nogil=True, cache=True)
def _galerkin_axis(S, cz, cy, cx, reach, axis, support, support_weight, rz, ry, rx, out):
    """One axis of ``Pᵀ A P``: ``out`` the half-stored class stencil after coarsening ``axis``.

    ``S`` is the fine half-stored class stencil (classes ``cz, cy, cx`` per fine position),
    ``support, support_weight`` (nc, 3) the fine nodes of each coarse node's hat along
    ``axis`` (:func:`axis_transfer`), ``rz, ry, rx`` a representative position of each
    output class (coarse positions along ``axis``, fine ones along the others). The reach
    stays the same (a coarse coupling ``|I - J|`` comes from fine ``|2I - 2J| ≤ reach + 2``).
    """
    w = 2 * reach + 1
    kc = (w * w * w - 1) // 2
    fine = np.array([len(cz), len(cy), len(cx)])
    coarse = fine.copy()
    coarse[axis] = support.shape[0]
    p = np.empty(3, np.int64)
    o = np.empty(3, np.int64)
    f = np.empty(3, np.int64)
    d = np.empty(3, np.int64)
    acc = np.empty((3, 3))
    for a in range(len(rz)):
        for b in range(len(ry)):
            for c in range(len(rx)):
                p[0], p[1], p[2] = rz[a], ry[b], rx[c]
                for h in range(kc + 1):
                    k = h + kc
                    o[0], o[1], o[2] = k // (w * w) - reach, (k // w) % w - reach, k % w - reach
                    inside = True
                    for t in range(3):
                        q = p[t] + o[t]
                        if q < 0 or q >= coarse[t]:
                            inside = False
                    acc[:] = 0.0
                    if inside:
                        pa, qa = p[axis], p[axis] + o[axis]
                        for s1 in range(3):
                            i = support[pa, s1]
                            if i < 0:
                                continue
                            for s2 in range(3):
                                j = support[qa, s2]
                                if j < 0 or abs(j - i) > reach:
                                    continue
                                wt = support_weight[pa, s1] * support_weight[qa, s2]
                                for t in range(3):
                                    f[t], d[t] = p[t], o[t]
                                f[axis], d[axis] = i, j - i
                                kk = ((d[0] + reach) * w + d[1] + reach) * w + d[2] + reach
                                if kk >= kc:
                                    blk = S[cz[f[0]], cy[f[1]], cx[f[2]], kk - kc]
                                    for u in range(3):
                                        for v in range(3):
                                            acc[u, v] += wt * blk[u, v]
                                else:  # the transpose of the neighbour's upper-half entry
                                    blk = S[cz[f[0] + d[0]], cy[f[1] + d[1]], cx[f[2] + d[2]], kc - kk]
                                    for u in range(3):
                                        for v in range(3):
                                            acc[u, v] += wt * blk[v, u]
                    for u in range(3):
                        for v in range(3):
                            out[a, b, c, h, u, v] = acc[u, v]


@dataclass
class ClassStencil:
    """A half-stored stencil whose rows repeat by per-axis class (:func:`class_map`).

    Attributes
    ----------
    S : ndarray, shape (Kz, Ky, Kx, ((2 reach + 1)³ + 1) / 2, 3, 3)
        Block rows, upper half of the offsets.
    classes : tuple of 3 ndarray (n,), int64
        Class of each node position per axis.
    reps : tuple of 3 ndarray (K,), int64
        One position of each class per axis.
    reach : int
        Offsets up to ``reach`` nodes per axis.
    """

    S: np.ndarray
    classes: tuple
    reps: tuple
    reach: int

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(len(c) for c in self.classes)

    def matvec_add(self, lam: float, x: np.ndarray, y: np.ndarray) -> None:
        """``y += lam A x`` for nodal fields (nz, ny, nx, 3), float64."""
        if not hasattr(self, "_sparsity"):
            # the nonzero blocks of each class row, and whether all blocks are diagonal
            nonzero = np.abs(self.S).reshape(-1, self.S.shape[3], 9).max(axis=2) > 0
            ptr = np.concatenate([[0], np.cumsum(nonzero.sum(axis=1))]).astype(np.int64)
            off = self.S.copy()
            off[..., [0, 1, 2], [0, 1, 2]] = 0
            self._sparsity = ptr, np.nonzero(nonzero)[1].astype(np.int64), not off.any()
        _class_matvec(self.S, *self.classes, self.reach, *self._sparsity, lam, x, y)

    def diagonal_blocks(self) -> np.ndarray:
        """The 3×3 diagonal blocks, shape (nz, ny, nx, 3, 3)."""
        return self.S[..., 0, :, :][np.ix_(*self.classes)]  # offset 0 first: not every offset's rows

    def coarsened(self, transfers, core: int) -> "ClassStencil":
        """``Pᵀ A P`` for the per-axis transfers (:func:`axis_transfer`; ``None`` keeps an axis)."""
        cur = self
        for axis, tr in enumerate(transfers):
            if tr is None:
                continue
            support, support_weight = tr[2], tr[3]
            cls, reps = class_map(support.shape[0], core) if core else (np.arange(support.shape[0]),) * 2
            new_reps = list(cur.reps)
            new_reps[axis] = reps
            new_classes = list(cur.classes)
            new_classes[axis] = cls
            out_shape = tuple(len(r) for r in new_reps) + cur.S.shape[3:]
            out = np.empty(out_shape, cur.S.dtype)
            _galerkin_axis(cur.S, *cur.classes, cur.reach, axis, support, support_weight, *new_reps, out)
            cur = ClassStencil(out, tuple(new_classes), tuple(new_reps), cur.reach)
        return cur


def node_stencil(H: np.ndarray) -> ClassStencil:
    """The per-node half stencil ``H`` (nz, ny, nx, 14, 3, 3) of ``M`` as a class stencil (no copy)."""
    classes = tuple(np.arange(n, dtype=np.int64) for n in H.shape[:3])
    return ClassStencil(H, classes, classes, 1)


def regularizer_stencil(reg: Regularizer) -> ClassStencil:
    """``R`` of ``reg`` as a reach-2 class stencil, probed on a mesh of at most 7³ nodes.

    A colouring with period 5 (columns whose reach-2 supports do not overlap) gives every
    column of ``R`` of the small mesh in 375 products; the row of node ``m`` towards
    ``m + d`` is the transpose of column ``m`` read at ``m + d`` (``R`` is symmetric).
    """
    reach, period = 2, 5
    core = FINE_CORE
    maps = [class_map(n, core) for n in reg.nodes_shape]
    small_shape = tuple(len(r) for _, r in maps)
    small = reg.plain()  # the plain penalty's operators, whatever the robust reweighting freed
    if small_shape != reg.nodes_shape:
        small = reg.resized(small_shape)
    w = 2 * reach + 1
    kc = (w**3 - 1) // 2
    offsets = np.array([(k // (w * w) - reach, (k // w) % w - reach, k % w - reach) for k in range(kc, w**3)])
    S = np.zeros(small_shape + (kc + 1, 3, 3))
    grid = np.indices(small_shape).reshape(3, -1).T
    colours = np.ravel_multi_index(tuple((grid % period).T), (period,) * 3)
    targets = grid[:, None, :] + offsets[None]  # (nodes, offsets, 3)
    ok = np.all((targets >= 0) & (targets < small_shape), axis=2)
    for colour in np.unique(colours):
        sel = colours == colour
        nodes, t, o = grid[sel], targets[sel], ok[sel]
        where = np.nonzero(o)
        for i in range(3):
            e = np.zeros(small_shape + (3,))
            e[tuple(nodes.T) + (i,)] = 1.0
            col = small.apply(e)
            S[tuple(nodes[where[0]].T) + (where[1], i)] = col[tuple(t[where].T)]
    return ClassStencil(S, tuple(m[0] for m in maps), tuple(m[1] for m in maps), reach)


# --- the hierarchy -------------------------------------------------------------------

def identity_transfer(n: int) -> tuple:
    fi = np.stack([np.arange(n), np.arange(n)], axis=1).astype(np.int64)
    fw = np.zeros((n, 2))
    fw[:, 0] = 1.0
    sup = np.full((n, 3), -1, np.int64)
    sup[:, 0] = np.arange(n)
    sw = np.zeros((n, 3))
    sw[:, 0] = 1.0
    return fi, fw, sup, sw


def level_transfers(shape) -> tuple | None:
    """Per-axis transfers to the next coarser level (``None`` entries: axis kept), or None at the bottom."""
    if int(np.prod(shape)) <= COARSEST or all(coarse_size(n) == n for n in shape):
        return None
    return tuple(axis_transfer(n) if coarse_size(n) < n else None for n in shape)


def matrix_hierarchy(H: np.ndarray) -> list[tuple]:
    """The Galerkin coarse ``M`` of the half stencil ``H``: ``[(shape, M_l, transfers_l), …]`` from fine to coarsest.

    ``M_0`` is ``H`` itself; ``transfers_l`` leads from level ``l`` to ``l + 1`` (None on the last).
    """
    out = []
    M = H
    while True:
        shape = M.shape[:3]
        tr = level_transfers(shape)
        out.append((shape, M, tr))
        if tr is None:
            return out
        M = coarsened_in_slabs(M, tr)


def coarsened_in_slabs(H: np.ndarray, transfers, slab: int = SLAB) -> np.ndarray:
    """``Pᵀ H P`` of a per-node half stencil ``H`` (nz, ny, nx, 14, 3, 3), a few coarse z planes at a time.

    The same products as :meth:`ClassStencil.coarsened`, but the intermediate after the
    first axis (half the fine stencil: 530 MB at 128³ nodes) never exists whole: each slab
    of ``slab`` coarse planes is coarsened along z, then y, then x, each step over the
    planes the next one reads (one more on each side per later step, since a coarse node
    couples with its neighbours). Returns the coarse half stencil, ``H``'s dtype.
    """
    if transfers[0] is None:  # z is not coarsened: nothing to slab along
        return node_stencil(H).coarsened(transfers, 0).S
    coarse = tuple(n if tr is None else tr[2].shape[0] for n, tr in zip(H.shape[:3], transfers))
    out = np.empty(coarse + H.shape[3:], H.dtype)
    steps = [axis for axis in range(3) if transfers[axis] is not None]
    fine = node_stencil(H)
    for a in range(0, coarse[0], slab):
        b = min(a + slab, coarse[0])
        cur = fine
        for i, axis in enumerate(steps):
            halo = len(steps) - 1 - i
            lo, hi = max(a - halo, 0), min(b + halo, coarse[0])
            reps, classes = list(cur.reps), list(cur.classes)
            reps[0] = np.arange(lo, hi, dtype=np.int64)
            classes[0] = np.zeros(coarse[0], np.int64)
            classes[0][lo:hi] = np.arange(hi - lo)
            if axis != 0:
                reps[axis] = classes[axis] = np.arange(coarse[axis], dtype=np.int64)
            part = np.empty(tuple(len(r) for r in reps) + H.shape[3:], H.dtype)
            _galerkin_axis(cur.S, *cur.classes, cur.reach, axis, transfers[axis][2], transfers[axis][3],
                           *reps, part)
            cur = ClassStencil(part, tuple(classes), tuple(reps), cur.reach)
        out[a:b] = cur.S
    return out


def regularizer_hierarchy(reg: Regularizer) -> list[ClassStencil]:
    """``[R_0, R_1, …]``: ``R`` of ``reg`` and its Galerkin coarsenings (cached on ``reg``: independent of ``λ``)."""
    cached = getattr(reg, "_multigrid", None)
    if cached is not None:
        return cached
    R = regularizer_stencil(reg)
    out = [R]
    while True:
        tr = level_transfers(R.shape)
        if tr is None:
            break
        R = R.coarsened(tr, CORE)
        out.append(R)
    reg._multigrid = out
    return out
