"""The DVC Challenge 2.0 definitions of a field's error, and the noise floor of repeated scans.

Against a known truth ``u_true`` (per component, over the points scored):

- **bias** ``μ = mean(u − u_true)``;
- **noise floor** ``σ``: the population standard deviation of ``u − u_true`` once the
  *translation only* is removed, i.e. about its mean ``μ`` (a rotation or a strain left in
  the error counts as noise: that is the definition, not a fit);
- ``u_rms = √(μ² + σ²)``, the RMS error.

Pooled over the components: ``σ = √(mean σ_i²)``, ``|μ| = √(mean μ_i²)``,
``u_rms = √(mean u_rms,i²)``.

Repeated scans of an unloaded specimen (the iDICs Good Practices Guide): each later scan
``k`` correlated against the first gives a field ``u_k`` whose truth is a rigid translation.
The **spatial** noise floor is the standard deviation over the points of one field about its
own mean (its translation), averaged over the fields (RMS); the **temporal** noise floor is,
at each point, the standard deviation over the fields of ``u_k − mean_points(u_k)`` (sample
standard deviation, ``k − 1`` in the denominator: a few fields), then the RMS over the
points: it needs at least two fields (three scans). Every field shares the first scan's
noise, which the temporal floor does not see: with independent noise of equal size in each
scan it is the spatial floor divided by √2. With a single pair the temporal floor is that one
field's deviation at each point from its own translation, i.e. the spatial floor itself, and
is reported as such.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["challenge_numbers", "noise_floors", "CHALLENGE_KEYS"]

#: the keys :func:`challenge_numbers` adds per component and pooled
CHALLENGE_KEYS = ("bias", "noise_floor", "u_rms")


def challenge_numbers(error: np.ndarray) -> dict:
    """Bias, noise floor and RMS of an error field (DVC Challenge 2.0, module docstring).

    Parameters
    ----------
    error : ndarray, shape (3, n), float64
        ``u − u_true`` per component ``(z, y, x)`` at the points scored (NaN left out).

    Returns
    -------
    dict
        ``bias_z/y/x``, ``noise_floor_z/y/x``, ``u_rms_z/y/x`` and the pooled ``bias``
        (``√(mean μ_i²)``), ``noise_floor``, ``u_rms``; ``points`` scored.

    Examples
    --------
    >>> e = np.array([[0.1, 0.3], [0.0, 0.0], [-0.2, -0.2]])
    >>> d = challenge_numbers(e)
    >>> round(d["bias_z"], 12), round(d["noise_floor_z"], 12), round(d["u_rms_z"], 12)
    (0.2, 0.1, 0.22360679775)
    """
    e = np.asarray(error, np.float64).reshape(3, -1)
    e = e[:, np.isfinite(e).all(axis=0)]
    out: dict = {"points": int(e.shape[1])}
    if e.shape[1] == 0:
        for key in CHALLENGE_KEYS:
            out[key] = math.nan
            out.update({f"{key}_{c}": math.nan for c in "zyx"})
        return out
    mu, sigma = e.mean(axis=1), e.std(axis=1)
    rms = np.sqrt(mu**2 + sigma**2)
    for key, v in (("bias", mu), ("noise_floor", sigma), ("u_rms", rms)):
        out.update({f"{key}_{c}": float(x) for c, x in zip("zyx", v)})
        out[key] = float(np.sqrt(np.mean(v**2)))
    return out


def noise_floors(fields) -> dict:
    """Spatial and temporal noise floors of fields measured between repeated scans (module docstring).

    Parameters
    ----------
    fields : sequence of ndarray, each shape (3, n), float64
        The fields ``u_k`` at the same ``n`` points (NaN where a point was not measured).

    Returns
    -------
    dict
        ``spatial_z/y/x``, ``temporal_z/y/x``, pooled ``spatial``, ``temporal`` (voxels, as
        the fields) and ``fields``, ``points``; ``temporal_from`` says which definition was
        used (``"fields"``, or ``"one field"`` for a single pair).
    """
    arr = np.stack([np.asarray(f, np.float64).reshape(3, -1) for f in fields])  # (k, 3, n)
    ok = np.isfinite(arr).all(axis=(0, 1))
    arr = arr[:, :, ok]
    dev = arr - arr.mean(axis=2, keepdims=True)  # each field about its own translation
    spatial = np.sqrt((dev.std(axis=2) ** 2).mean(axis=0))
    if arr.shape[0] >= 2:
        temporal = np.sqrt((dev.std(axis=0, ddof=1) ** 2).mean(axis=1))
        how = "fields"
    else:
        temporal = np.sqrt((dev[0] ** 2).mean(axis=1))
        how = "one field"
    out = {"fields": int(arr.shape[0]), "points": int(arr.shape[2]), "temporal_from": how}
    for key, v in (("spatial", spatial), ("temporal", temporal)):
        out.update({f"{key}_{c}": float(x) for c, x in zip("zyx", v)})
        out[key] = float(np.sqrt(np.mean(v**2)))
    return out
