"""The noise floor of repeated scans of an unloaded specimen (iDICs Good Practices Guide).

``chunkdic uncertainty SCAN --repeat SCAN2 [SCAN3 …]``: instead of a Fourier-shifted copy of
one scan (the paper's a-priori test, where the noise of the pair is the scan's own), the
repeats are real acquisitions: their noise, drift and small motions are those of the machine.
Each repeat is correlated against the first scan for each element size (no regularisation,
as the a-priori test: the C8 basis itself), and per element size the table gives, over the
nodes at least ``ℓ`` from the faces (:func:`chunkdic.analysis.scoring.scored_region`):

- the **spatial** and **temporal** noise floors (:func:`chunkdic.analysis.challenge.noise_floors`);
- the DVC Challenge 2.0 **bias** ``μ`` (the mean displacement: between repeats of an unloaded
  specimen it is the specimen's motion plus the measurement's bias, which one pair cannot
  separate) and ``u_rms = √(μ² + σ²)`` with the truth taken as zero motion.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..engine.driver import correlate
from ..errors import InputError
from ..io.outputs import Outputs
from ..io.scan import open_scan
from ..scheduler import check_scheduler
from .challenge import challenge_numbers, noise_floors
from ..method.settings import Settings
from .metrology import PAPER_SETTINGS, check_element_sizes, check_plan, study_settings, write_table
from .scoring import scored_region

log = logging.getLogger(__name__)

__all__ = ["RepeatReport", "repeat_noise", "REPEAT_COLUMNS"]

REPEAT_COLUMNS = [
    ("element_size", "ZOI size (vox.)", "d"),
    ("spatial_z", "spatial σ Uz (vox.)", ".4f"), ("spatial_y", "spatial σ Uy (vox.)", ".4f"),
    ("spatial_x", "spatial σ Ux (vox.)", ".4f"), ("spatial", "spatial σ (vox.)", ".4f"),
    ("temporal", "temporal σ (vox.)", ".4f"), ("temporal_from", "temporal from", "s"),
    ("bias", "|μ| (vox.)", ".4f"), ("u_rms", "u_rms (vox.)", ".4f"),
    ("fields", "fields", "d"), ("points", "nodes", "d"), ("status", "status", "s"),
]


@dataclass
class RepeatReport:
    """Outcome of :func:`repeat_noise`: one row per element size (:data:`REPEAT_COLUMNS`) and the files."""

    rows: list[dict]
    files: dict = field(default_factory=dict)

    def markdown(self) -> str:
        return ("Noise floor of repeated scans of an unloaded specimen (iDICs guide; DVC Challenge 2.0 bias and "
                "u_rms against zero motion)\n\n" + write_table(self.rows, REPEAT_COLUMNS))


def repeat_noise(scans: Sequence, element_sizes: Sequence[int], out_dir, settings: Settings | None = None, *,
                 roi=None, roi_unit: str | None = None, scheduler=None, overwrite: bool = False,
                 progress: Callable[[dict], None] | None = None, **options) -> RepeatReport:
    """Spatial and temporal noise floors of repeated scans (module docstring).

    Parameters
    ----------
    scans : sequence of path
        Two or more scans of the unloaded specimen; the first is the reference.
    element_sizes : sequence of int
        Element edges, voxels of ``level``.
    out_dir : path
        Folder for the results (``result-ell{ell}-repeat{k}.zarr``), ``uncertainty.csv`` and
        ``uncertainty.md`` (an ``uncertainty`` folder, as the a-priori test's).
    settings, roi, roi_unit, scheduler, overwrite, progress, **options
        As in :func:`chunkdic.analysis.metrology.uncertainty` (without ``settings``, no
        regularisation unless ``options`` asks for one).

    Returns
    -------
    RepeatReport
    """
    scans = list(scans)
    if len(scans) < 2:
        raise InputError("--repeat needs at least one more scan of the unloaded specimen")
    sizes = check_element_sizes(element_sizes)
    opened = [open_scan(s) for s in scans]
    shape = tuple(opened[0].shape(0))
    for path, sc in zip(scans[1:], opened[1:]):
        if tuple(sc.shape(0)) != shape:
            raise InputError(f"repeat {path}: shape {tuple(sc.shape(0))} is not the first scan's {shape}")
    given = study_settings(settings, options, PAPER_SETTINGS)
    check_plan(scans[0], scans[1], sizes, given, roi=roi, roi_unit=roi_unit, caller="uncertainty --repeat")
    level = int(given.get("level", 0))
    check_scheduler(scheduler)
    plan = Outputs(inputs=scans, overwrite=overwrite)
    out = plan.add(out_dir, "uncertainty").final
    emit = progress or (lambda event: None)
    rows = []
    with plan:
        for ell in sizes:
            emit({"stage": "element-size", "element_size": ell})
            fields, statuses = [], []
            for k, other in enumerate(scans[1:], 1):
                res = correlate(scans[0], other, element_size=ell, roi=roi, roi_unit=roi_unit, **given, scheduler=scheduler,
                                output=out / f"result-ell{ell}-repeat{k}.zarr", overwrite=True, progress=progress)
                level_shape = tuple(int(n) >> int(level) for n in shape)
                inside = scored_region(res.node_coords, level_shape, ell)
                fields.append(res.displacement.reshape(3, -1)[:, inside])
                statuses.append(str(res.info.get("status")))
            floors = noise_floors(fields)
            challenge = challenge_numbers(np.concatenate(fields, axis=1))
            row = {"element_size": ell, **floors, "bias": challenge["bias"], "u_rms": challenge["u_rms"],
                   **{f"bias_{c}": challenge[f"bias_{c}"] for c in "zyx"},
                   "status": ",".join(sorted(set(statuses)))}
            log.info("repeat noise floor, ell %d: %s", ell, row)
            rows.append(row)
            emit({"stage": "repeat", **row})
        report = RepeatReport(rows)
        files = {"csv": str(out / "uncertainty.csv"), "markdown": str(out / "uncertainty.md")}
        keys = [k for k, _, _ in REPEAT_COLUMNS] + [k for k in rows[0] if k not in {c for c, _, _ in REPEAT_COLUMNS}]
        write_table(rows, [(k, k, "") for k in keys], files["csv"])
        Path(files["markdown"]).write_text(report.markdown())
    report.files = files
    return report
