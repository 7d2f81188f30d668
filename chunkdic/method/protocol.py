"""What the method asks of the voxels of one level: the passes, and the values they return.

The method (:mod:`chunkdic.method`) holds mesh-sized data only: nodal fields, ``M``'s
stencil and solver, ``b``, per-element brightness. Everything that reads voxels is a
*pass* of a :class:`Passes` object, whose results come back as values:

- :meth:`Passes.assemble_m` sums ``M`` for a field and returns it as a frozen
  :class:`~chunkdic.method.operator.Operator` (paper section 3: built once per level, from
  the reference);
- :meth:`Passes.assemble_b` sums one modified Gauss–Newton pass for a field and returns a
  :class:`Pass` (``b``, the brightness found, the gap, voxel counts, the noise correlation);
- :meth:`Passes.gap` measures a field's matching gap alone (paper section 5.1), on a
  sample of elements;
- :meth:`Passes.prepare` makes the passes ready for fields near a given one (out of core:
  the low-pass and B-spline prefilter of the part of ``g`` it reaches) and
  :meth:`Passes.covers` says whether a field needs no further preparation;
- :meth:`Passes.translation` is the integer translation of phase correlation;
- :meth:`Passes.park` keeps a mesh-sized array the iterations do not read out of the
  client's memory where the level's mesh data do not fit it.

Two implementations: the out-of-core block passes (:class:`chunkdic.passes.level.LevelPasses`,
tasks over Zarr stores) and a dense twin on in-memory arrays
(:class:`chunkdic.passes.dense.DensePasses`), on which the tests run the whole method.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np

from ..mesh import Mesh
from .brightness import Fit
from .operator import Operator

__all__ = ["Pass", "Passes", "stack_rows"]


@dataclasses.dataclass
class Pass:
    """One ``b`` pass over a level for a nodal field.

    Attributes
    ----------
    fit : Fit
        ``b``, ``Σ r²`` and the brightness found (:mod:`chunkdic.method.brightness`).
    gap : float
        Matching gap ``rms(r) / (max f - min f)`` over the valid voxels (paper section 5.1).
    n_valid, n_excluded : int
        Voxels used, and voxels whose ``X + u(X)`` left ``g``.
    kappa : float
        How much more misfit a fitted unknown absorbs than with white noise
        (:func:`chunkdic.method.noise.correlation_factor`).
    probe_gaps : dict
        The gaps of the further fields the pass measured (:meth:`Passes.assemble_b`'s ``probes``).
    seconds : float
        Wall time of the pass.
    b_other : ndarray, shape (K, 3), float64, optional
        ``b`` of the second copies of the nodes a known crack splits
        (:mod:`chunkdic.method.crack`), None without one.
    """

    fit: Fit
    gap: float
    n_valid: int
    n_excluded: int
    kappa: float = 1.0
    probe_gaps: dict = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    b_other: np.ndarray | None = None

    @property
    def noise_variance(self) -> float:
        """``σ_r²``: the mean squared residual (grey levels²)."""
        return self.fit.ssr / self.fit.weight if self.fit.weight > 0 else float("nan")

    @property
    def b(self) -> np.ndarray:
        return self.fit.b

    @property
    def excluded_fraction(self) -> float:
        total = self.n_valid + self.n_excluded
        return self.n_excluded / total if total else 1.0


class Passes(Protocol):
    """The passes over the voxels of one pyramid level (module docstring).

    Attributes
    ----------
    level : int
        The pyramid level.
    mesh : Mesh
        Its mesh; every nodal field has shape ``(3,) + mesh.nodes_shape``, float64, voxels
        of the level.
    """

    level: int
    mesh: Mesh

    def assemble_m(self, u: np.ndarray) -> Operator:
        """``M`` for the field ``u`` (voxels it maps outside ``g`` left out), as an operator."""

    def prepare(self, u: np.ndarray) -> None:
        """Be ready to evaluate fields near ``u`` (a no-op when :meth:`covers` says so)."""

    def covers(self, u: np.ndarray) -> bool:
        """Whether ``u`` needs no preparation beyond what is done."""

    def assemble_b(self, u: np.ndarray, op: Operator, *, sample: np.ndarray | None = None,
                   probes: dict[str, np.ndarray] | None = None, other: np.ndarray | None = None) -> Pass:
        """One pass for ``u`` with the operator ``op``'s element activity and centring;
        ``sample``: only these elements (uint8, the mesh's element shape); ``probes``: named
        fields whose gap alone is measured in the same pass, on :meth:`gap`'s sample;
        ``other``: the second copies (K, 3) of ``op.crack``'s split nodes (None: ``u`` there)."""

    def park(self, array):
        """``array`` (an ndarray, or a list of its rows along a first axis, stacked by
        :func:`stack_rows`), or where the level's mesh data do not fit the client (node blocks)
        an array-like kept out of its memory, written row by row, that ``np.asarray`` reads
        back: for mesh-sized arrays the Gauss–Newton loop does not read until the level ends
        (the best field, the element fields, a pass's ``b`` while it is solved for)."""

    def gap(self, u: np.ndarray, op: Operator) -> float:
        """The matching gap of ``u`` alone (a diagnostic), on a sample of elements of large meshes."""

    def translation(self) -> np.ndarray:
        """The integer translation (3,) of phase correlation over the level's ROI, voxels of the level."""


def stack_rows(array) -> np.ndarray:
    """``array`` itself if an ndarray, else its rows (a list of arrays of one shape, some
    perhaps broadcast) stacked along a new first axis in their common dtype, filled row by row
    (no stacked temporary besides the result)."""
    if isinstance(array, np.ndarray):
        return array
    out = np.empty((len(array),) + np.shape(array[0]), dtype=np.result_type(*array))
    for k, row in enumerate(array):
        out[k] = row
    return out
