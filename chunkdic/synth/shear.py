"""Shear fields along x that vary with z: sinusoidal waves and a localised slip.

``Ux = h(Z)``, ``Uz = Uy = 0``: the deformed position keeps ``z``, so the inverse is exact
(``X = x - h(z)``). :class:`Wave` (``h = A sin(2π (Z - phase) / period)``) probes how short
a feature a setting follows; :class:`Slip` (``h = (jump / 2) tanh((Z - center) / edge)``)
is a localised shear band. Both round-trip through ``Field.to_json`` / ``from_json``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import InputError
from .fields import Field, _xyz

__all__ = ["Wave", "Slip"]


class _ShearProfile(Field):
    """``Ux = h(Z)`` for a profile ``h`` of ``Z`` alone (subclasses give :meth:`_h`)."""

    def _h(self, z: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def displacement(self, z, y, x):
        zz, _, _ = _xyz(z, y, x)
        zero = np.zeros(zz.shape)
        return np.stack([zero, zero, self._h(zz)])

    def inverse(self, z, y, x):
        zz, yy, xx = _xyz(z, y, x)
        return np.stack([zz, yy.copy(), xx - self._h(zz)])

    def _check(self, **values) -> None:
        for name, v in values.items():
            if not math.isfinite(float(v)):
                raise InputError(f"{self.kind} parameter {name} must be finite, got {v!r}")
            object.__setattr__(self, name, float(v))


@dataclass(frozen=True)
class Wave(_ShearProfile):
    """Sinusoidal shear wave ``Ux = amplitude · sin(2π (Z - phase) / period)``.

    Parameters
    ----------
    period : float, voxels
    amplitude : float, voxels
        Kept below ``period / (2π)`` so that the map stays invertible (it always is here:
        ``x - h(z)`` is explicit; the bound keeps the shear strain below 1).
    phase : float, voxels
    """

    kind: ClassVar[str] = "wave"
    period: float = 32.0
    amplitude: float = 0.5
    phase: float = 0.0

    def __post_init__(self):
        self._check(period=self.period, amplitude=self.amplitude, phase=self.phase)
        if self.period <= 0:
            raise InputError(f"wave period must be positive, got {self.period}")
        if 2 * math.pi * abs(self.amplitude) >= self.period:
            raise InputError("wave amplitude must stay below period / (2π) (shear strain < 1)")

    def _h(self, z):
        return self.amplitude * np.sin(2 * np.pi * (z - self.phase) / self.period)

    def _json_fields(self):
        return {"period": self.period, "amplitude": self.amplitude, "phase": self.phase}


@dataclass(frozen=True)
class Slip(_ShearProfile):
    """Localised shear slip ``Ux = (jump / 2) · tanh((Z - center) / edge)``.

    Parameters
    ----------
    center : float, voxels
    jump : float, voxels
        Total slip across the band.
    edge : float, voxels
        Half-width scale of the band (shear strain peaks at ``jump / (2 edge)``).
    """

    kind: ClassVar[str] = "slip"
    center: float = 0.0
    jump: float = 1.0
    edge: float = 4.0

    def __post_init__(self):
        self._check(center=self.center, jump=self.jump, edge=self.edge)
        if self.edge <= 0:
            raise InputError(f"slip edge must be positive, got {self.edge}")

    def _h(self, z):
        return 0.5 * self.jump * np.tanh((z - self.center) / self.edge)

    def _json_fields(self):
        return {"center": self.center, "jump": self.jump, "edge": self.edge}
