"""Analytic displacement fields of the synthetic specimens, in voxels.

A :class:`Field` gives the displacement ``u(X)`` in the reference (Lagrangian) frame and
its inverse ``X(x)`` with ``X + u(X) = x``; :mod:`chunkdic.synth.foam` renders a deformed
scan as ``g(x) = f(X(x))``. Fields: :class:`Translation` (rigid), :class:`Affine` (exact
inverse), :class:`Band`, the paper's localized compression band (inverse by Newton to
1e-13), and :class:`Star`, a sine along z whose period rises across y (the DIC Challenge
2.0 star, for the spatial resolution; explicit inverse), :class:`Crack`, a planar crack
(a displacement jump), and :class:`Composed`, one field's motion followed by another's (a
crack under compression). Every field has ``to_json()`` and ``Field.from_json(d)``, so that it round-trips
through a pair's ``field.json``. All names are re-exported by :mod:`chunkdic.synth.synthetic`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numba import njit

from ..errors import InputError

__all__ = [
    "Field",
    "Translation",
    "Affine",
    "Band",
    "Star",
    "Crack",
    "Composed",
    "true_displacement",
]


class Field(ABC):
    """A displacement field ``u(X)`` in the reference (Lagrangian) frame, in voxels.

    Subclasses are frozen dataclasses. ``x = X + u(X)`` is the position in the deformed
    scan of the material point at ``X`` in the reference scan.
    """

    kind: ClassVar[str] = ""
    _registry: ClassVar[dict[str, type]] = {}

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.kind:
            Field._registry[cls.kind] = cls

    @abstractmethod
    def displacement(self, z, y, x) -> np.ndarray:
        """Displacement ``u(X)``.

        Parameters
        ----------
        z, y, x : array_like, broadcastable, float64, voxels
            Reference positions ``X``.

        Returns
        -------
        ndarray, shape (3, *shape), float64, voxels
            Components ``(Uz, Uy, Ux)``.
        """

    @abstractmethod
    def inverse(self, z, y, x) -> np.ndarray:
        """Reference positions ``X`` with ``X + u(X) = x``.

        Parameters
        ----------
        z, y, x : array_like, broadcastable, float64, voxels
            Deformed positions ``x``.

        Returns
        -------
        ndarray, shape (3, *shape), float64, voxels
        """

    @abstractmethod
    def _json_fields(self) -> dict:
        ...

    def to_json(self) -> dict:
        """A JSON-serialisable dict; :meth:`Field.from_json` reads it back."""
        return {"type": self.kind, **self._json_fields()}

    @classmethod
    def from_json(cls, d: dict) -> "Field":
        """Build the field described by ``d`` (the output of :meth:`to_json`)."""
        d = dict(d)
        kind = d.pop("type", None)
        if kind not in Field._registry:
            raise InputError(f"unknown field type {kind!r} (known: {sorted(Field._registry)})")
        try:
            return Field._registry[kind]._from_fields(d)
        except (TypeError, KeyError) as exc:
            raise InputError(f"bad {kind} field description {d!r}: {exc}") from None

    @classmethod
    def _from_fields(cls, d: dict) -> "Field":
        return cls(**d)


def _xyz(z, y, x):
    return np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (z, y, x)))


def _vec3(v, name) -> tuple[float, float, float]:
    t = tuple(float(a) for a in np.asarray(v, dtype=np.float64).ravel())
    if len(t) != 3 or not all(np.isfinite(t)):
        raise InputError(f"{name} must be 3 finite numbers (z, y, x), got {v!r}")
    return t


@dataclass(frozen=True)
class Translation(Field):
    """Rigid translation ``u(X) = t``.

    Parameters
    ----------
    t : tuple of 3 float, voxels
        ``(tz, ty, tx)``.
    """

    kind: ClassVar[str] = "translation"
    t: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "t", _vec3(self.t, "t"))

    def displacement(self, z, y, x):
        zz, _, _ = _xyz(z, y, x)
        return np.stack([np.full(zz.shape, c) for c in self.t])

    def inverse(self, z, y, x):
        zz, yy, xx = _xyz(z, y, x)
        return np.stack([zz - self.t[0], yy - self.t[1], xx - self.t[2]])

    def _json_fields(self):
        return {"t": list(self.t)}


@dataclass(frozen=True)
class Affine(Field):
    """Affine field ``u(X) = A (X - center) + translation``.

    Parameters
    ----------
    matrix : 3x3 nested tuple of float
        Displacement gradient ``A[i][j] = dU_i / dX_j``, axes ``(z, y, x)``.
    center : tuple of 3 float, voxels
        Point where ``u = translation``.
    translation : tuple of 3 float, voxels
    """

    kind: ClassVar[str] = "affine"
    matrix: tuple = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        a = np.asarray(self.matrix, dtype=np.float64)
        if a.shape != (3, 3) or not np.all(np.isfinite(a)):
            raise InputError(f"affine matrix must be 3x3 finite numbers, got {self.matrix!r}")
        if abs(np.linalg.det(np.eye(3) + a)) < 1e-6 or np.linalg.det(np.eye(3) + a) < 0:
            raise InputError("affine field is not invertible (det(I + A) <= 0)")
        object.__setattr__(self, "matrix", tuple(tuple(float(v) for v in r) for r in a))
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        object.__setattr__(self, "translation", _vec3(self.translation, "translation"))

    def displacement(self, z, y, x):
        X = _xyz(z, y, x)
        d = [X[j] - self.center[j] for j in range(3)]
        a = self.matrix
        return np.stack([
            a[i][0] * d[0] + a[i][1] * d[1] + a[i][2] * d[2] + self.translation[i]
            for i in range(3)
        ])

    def inverse(self, z, y, x):
        xs = _xyz(z, y, x)
        b = np.linalg.inv(np.eye(3) + np.asarray(self.matrix))
        d = [xs[j] - self.center[j] - self.translation[j] for j in range(3)]
        return np.stack([
            self.center[i] + (b[i, 0] * d[0] + b[i, 1] * d[1] + b[i, 2] * d[2])
            for i in range(3)
        ])

    def _json_fields(self):
        return {
            "matrix": [list(r) for r in self.matrix],
            "center": list(self.center),
            "translation": list(self.translation),
        }

    @classmethod
    def _from_fields(cls, d):
        return cls(matrix=tuple(tuple(r) for r in d["matrix"]), center=tuple(d["center"]),
                   translation=tuple(d["translation"]))


@njit(nogil=True, cache=True)
def _lncosh(a):
    a = abs(a)
    return a + math.log1p(math.exp(-2.0 * a)) - math.log(2.0)


@njit(nogil=True, cache=True)
def _band_profile(s, half, edge):
    # smooth top hat of width 2*half, value 1 inside, 0 outside, tanh edges of scale edge
    return 0.5 * (math.tanh((s + half) / edge) - math.tanh((s - half) / edge))


@njit(nogil=True, cache=True)
def _band_integral(s, half, edge):
    # integral of the profile from 0 to s (odd in s)
    return 0.5 * edge * (_lncosh((s + half) / edge) - _lncosh((s - half) / edge))


@njit(nogil=True, cache=True)
def _band_inverse_z(xz, cz, half, edge, strain, out):
    """Solve Z + strain * I(Z - cz) = xz per element (Newton, own stopping per element)."""
    for i in range(xz.size):
        target = xz[i] - cz
        s = target  # u_z is at most |strain| * half away from it
        for _ in range(100):
            r = s + strain * _band_integral(s, half, edge) - target
            step = r / (1.0 + strain * _band_profile(s, half, edge))
            s -= step
            if abs(step) < 1e-13 * (1.0 + abs(s)):
                break
        out[i] = s + cz


@dataclass(frozen=True)
class Band(Field):
    """Localized compression band normal to z with lateral expansion (the paper's case).

    With ``s = Z - center_z`` and ``p(s)`` a smooth top hat of width ``width`` (tanh
    edges of scale ``edge``) and ``I(s)`` its integral from 0:

    - ``Uz = strain * I(s)`` (strain ``< 0``: compression inside the band, rigid shifts of
      ``strain * width / 2`` on both sides, so the band shortens by ``|strain| * width``),
    - ``Uy = -lateral * strain * p(s) * (Y - center_y)``, same for ``x``.

    ``dUz/dZ = strain * p(s)``, so the field is smooth (C-infinity) and invertible for
    ``strain > -1``; the inverse solves the 1-D ``z`` equation by Newton to 1e-13 and the
    lateral components exactly.

    Parameters
    ----------
    center_z : float, voxels
    width : float, voxels
        Band width (full width at half of the profile).
    strain : float
        Axial strain inside the band (negative = compression), e.g. ``-0.05``.
    lateral : float
        Poisson-like lateral expansion factor (``0`` for a foam that does not expand).
    center_y, center_x : float, voxels
        Axis of the lateral expansion.
    edge : float or None, voxels
        Softness of the band edges (default ``width / 8``).
    """

    kind: ClassVar[str] = "band"
    center_z: float = 0.0
    width: float = 32.0
    strain: float = -0.05
    lateral: float = 0.3
    center_y: float = 0.0
    center_x: float = 0.0
    edge: float | None = None

    def __post_init__(self):
        for name in ("center_z", "width", "strain", "lateral", "center_y", "center_x"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise InputError(f"band parameter {name} must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        if self.width <= 0:
            raise InputError(f"band width must be positive, got {self.width}")
        if not -1.0 < self.strain < 1.0:
            raise InputError(f"band strain must lie in (-1, 1), got {self.strain}")
        if self.edge is not None:
            if not float(self.edge) > 0:
                raise InputError(f"band edge must be positive, got {self.edge!r}")
            object.__setattr__(self, "edge", float(self.edge))
        if abs(self.lateral * self.strain) >= 1.0:
            raise InputError("band lateral * strain must have magnitude < 1")

    @property
    def _edge(self) -> float:
        return self.edge if self.edge is not None else self.width / 8.0

    def _profile(self, s):
        e, h = self._edge, self.width / 2.0
        return 0.5 * (np.tanh((s + h) / e) - np.tanh((s - h) / e))

    def _integral(self, s):
        e, h = self._edge, self.width / 2.0

        def lncosh(a):
            a = np.abs(a)
            return a + np.log1p(np.exp(-2.0 * a)) - math.log(2.0)

        return 0.5 * e * (lncosh((s + h) / e) - lncosh((s - h) / e))

    def displacement(self, z, y, x):
        zz, yy, xx = _xyz(z, y, x)
        s = zz - self.center_z
        p = self._profile(s)
        k = -self.lateral * self.strain
        return np.stack([self.strain * self._integral(s), k * p * (yy - self.center_y),
                         k * p * (xx - self.center_x)])

    def inverse(self, z, y, x):
        zz, yy, xx = _xyz(z, y, x)
        # Z depends on z alone: solve on z as given (e.g. one value per plane of a grid),
        # then broadcast; element by element the result is the same
        z0 = np.asarray(z, dtype=np.float64)
        Z = np.empty(z0.size)
        _band_inverse_z(np.ascontiguousarray(z0).ravel(), self.center_z, self.width / 2.0,
                        self._edge, self.strain, Z)
        Z = Z.reshape(z0.shape)
        g = 1.0 - self.lateral * self.strain * self._profile(Z - self.center_z)
        Z, g = np.broadcast_to(Z, zz.shape), np.broadcast_to(g, zz.shape)
        return np.stack([Z, self.center_y + (yy - self.center_y) / g,
                         self.center_x + (xx - self.center_x) / g])

    def _json_fields(self):
        return {"center_z": self.center_z, "width": self.width, "strain": self.strain,
                "lateral": self.lateral, "center_y": self.center_y, "center_x": self.center_x,
                "edge": self.edge}


@dataclass(frozen=True)
class Star(Field):
    """3-D star: ``Ux = amplitude * sin(2 pi (Z - center_z) / period(Y))``, ``Uz = Uy = 0``.

    The period rises linearly across y, ``period(Y) = period_min + (period_max - period_min)
    * clip((Y - y0) / (y1 - y0), 0, 1)``, so one scan shows the field at every period from
    ``period_min`` to ``period_max`` (the star of the DIC Challenge 2.0, Reu et al. 2022, in
    3-D): a DVC code's measured/imposed amplitude along y gives its spatial resolution
    ``l10 %`` (:mod:`chunkdic.analysis.resolution`). The phase is zero on the plane
    ``Z = center_z``, where the fringes of all periods are aligned.

    ``u`` depends on ``(Z, Y)`` alone and moves points along x only, so the inverse is
    explicit: ``X = (z, y, x - Ux(z, y))``.

    Parameters
    ----------
    amplitude : float, voxels
    period_min, period_max : float, voxels
        Periods at ``y0`` and ``y1`` (positive).
    y0, y1 : float, voxels
        Where the period is ``period_min`` and ``period_max`` (``y0 != y1``); constant
        beyond them.
    center_z : float, voxels
        Plane of zero phase.
    """

    kind: ClassVar[str] = "star"
    amplitude: float = 0.5
    period_min: float = 16.0
    period_max: float = 160.0
    y0: float = 0.0
    y1: float = 255.0
    center_z: float = 0.0

    def __post_init__(self):
        for name in ("amplitude", "period_min", "period_max", "y0", "y1", "center_z"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise InputError(f"star parameter {name} must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        if self.period_min <= 0 or self.period_max <= 0:
            raise InputError(f"star periods must be positive, got {self.period_min}, {self.period_max}")
        if self.y1 == self.y0:
            raise InputError("star y0 and y1 must differ")

    def period(self, y) -> np.ndarray:
        """Period of the sine at ``y``, voxels (float64, shape of ``y``)."""
        s = np.clip((np.asarray(y, dtype=np.float64) - self.y0) / (self.y1 - self.y0), 0.0, 1.0)
        return self.period_min + (self.period_max - self.period_min) * s

    def _ux(self, zz, yy):
        return self.amplitude * np.sin(2.0 * np.pi * (zz - self.center_z) / self.period(yy))

    def displacement(self, z, y, x):
        zz, yy, _ = _xyz(z, y, x)
        ux = self._ux(zz, yy)
        zero = np.zeros(zz.shape)
        return np.stack([zero, zero, ux])

    def inverse(self, z, y, x):
        zz, yy, xx = _xyz(z, y, x)
        return np.stack([zz, yy, xx - self._ux(zz, yy)])

    def _json_fields(self):
        return {"amplitude": self.amplitude, "period_min": self.period_min, "period_max": self.period_max,
                "y0": self.y0, "y1": self.y1, "center_z": self.center_z}


@dataclass(frozen=True)
class Crack(Field):
    """A planar crack through the whole volume: a displacement jump across the plane.

    ``u(X) = ± jump / 2`` on the two sides of the plane through ``point`` with unit normal
    ``normal`` (``+`` where ``normal · (X − point) ≥ 0``), ``jump = opening · normal + sliding``
    (``sliding`` is made tangent to the plane). The opened gap (``|normal · (x − point)| <
    opening / 2`` in the deformed scan) has no material point: its texture is the crack faces'
    stretched across it, ``X(x) = x − jump · normal · (x − point) / opening``, so the deformed
    scan stays continuous and the jump is the only discontinuity of the motion.

    Parameters
    ----------
    normal : tuple of 3 float
        Normal of the crack plane ``(z, y, x)`` (normalised here).
    point : tuple of 3 float, voxels
        A point of the plane.
    opening : float, voxels
        Normal jump (``>= 0``).
    sliding : tuple of 3 float, voxels
        Tangential jump (its normal part is removed).
    """

    kind: ClassVar[str] = "crack"
    normal: tuple[float, float, float] = (1.0, 0.0, 0.0)
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    opening: float = 0.0
    sliding: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        n = np.asarray(_vec3(self.normal, "crack normal"))
        if not np.linalg.norm(n) > 0:
            raise InputError("the crack normal must not be zero")
        n = n / np.linalg.norm(n)
        opening = float(self.opening)
        if not (np.isfinite(opening) and opening >= 0):
            raise InputError(f"the crack opening must be >= 0 voxels, got {self.opening!r}")
        t = np.asarray(_vec3(self.sliding, "crack sliding"))
        object.__setattr__(self, "normal", tuple(float(v) for v in n))
        object.__setattr__(self, "point", _vec3(self.point, "crack point"))
        object.__setattr__(self, "opening", opening)
        object.__setattr__(self, "sliding", tuple(float(v) for v in t - (t @ n) * n))

    @property
    def jump(self) -> np.ndarray:
        """The displacement jump across the plane, ``opening · normal + sliding`` (3,), voxels."""
        return self.opening * np.asarray(self.normal) + np.asarray(self.sliding)

    def _side(self, X):
        return sum((X[j] - self.point[j]) * self.normal[j] for j in range(3))

    def displacement(self, z, y, x):
        X = _xyz(z, y, x)
        sign = np.where(self._side(X) >= 0, 0.5, -0.5)
        return np.stack([sign * self.jump[i] for i in range(3)])

    def inverse(self, z, y, x):
        xs = _xyz(z, y, x)
        s = self._side(xs)
        half = self.opening / 2.0
        if half > 0:  # the gap: the faces' texture stretched across it (continuous at both faces)
            frac = np.where(s >= half, 0.5, np.where(s <= -half, -0.5, s / (2.0 * half)))
        else:
            frac = np.where(s >= 0, 0.5, -0.5)
        return np.stack([xs[i] - frac * self.jump[i] for i in range(3)])

    def _json_fields(self):
        return {"normal": list(self.normal), "point": list(self.point), "opening": self.opening,
                "sliding": list(self.sliding)}

    @classmethod
    def _from_fields(cls, d):
        return cls(normal=tuple(d["normal"]), point=tuple(d["point"]), opening=float(d["opening"]),
                   sliding=tuple(d.get("sliding", (0.0, 0.0, 0.0))))


@dataclass(frozen=True)
class Composed(Field):
    """The motion of ``first`` followed by that of ``then``: a material point at ``X`` goes to
    ``X + u₁(X)``, then by ``then``'s field at that position, ``u(X) = u₁(X) + u₂(X + u₁(X))``.
    The inverse is exact where both fields' are: ``X(x) = X₁(X₂(x))``. For a feature under a
    large deformation (a crack, then 10 % compression), where the benchmark fields are each
    one alone.

    Parameters
    ----------
    first, then : Field
    """

    kind: ClassVar[str] = "composed"
    first: Field
    then: Field

    def __post_init__(self):
        for name in ("first", "then"):
            if not isinstance(getattr(self, name), Field):
                raise InputError(f"composed field: {name} must be a Field, got {getattr(self, name)!r}")

    def displacement(self, z, y, x):
        X = np.stack(_xyz(z, y, x))
        u1 = self.first.displacement(*X)
        return u1 + self.then.displacement(*(X + u1))

    def inverse(self, z, y, x):
        return self.first.inverse(*self.then.inverse(z, y, x))

    def _json_fields(self):
        return {"first": self.first.to_json(), "then": self.then.to_json()}

    @classmethod
    def _from_fields(cls, d):
        return cls(first=Field.from_json(d["first"]), then=Field.from_json(d["then"]))


def true_displacement(field: Field, z, y, x) -> np.ndarray:
    """The true displacement ``u(X)``, shape ``(3, *shape)``, float64, voxels.

    Same as ``field.displacement(z, y, x)``; ``field=None`` means no motion.
    """
    if field is None:
        zz, _, _ = _xyz(z, y, x)
        return np.zeros((3, *zz.shape))
    return field.displacement(z, y, x)
