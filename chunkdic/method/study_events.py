"""The events of the studies: one typed record per stage of a series, an uncertainty test, a
sweep, a resolution study, a repeat-scan study, a cut check and a report's figures.

They are :class:`chunkdic.method.events.Event` subclasses: each words itself, :func:`emit` logs
it and hands it to the caller's ``progress`` callback, and the CLI prints it through the same
:class:`~chunkdic.method.events.EventText` as the correlations' events (which a study passes on
unchanged, between its own). A row event carries the study's table row as it is written to
its CSV file (``row``, the columns of the study's ``*_COLUMNS``).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any, ClassVar

from .events import Event, emit

__all__ = ["StudyEvent", "SeriesStep", "ElementSize", "APriori", "StepShare", "UncertaintyRow", "ResolutionRow",
           "RepeatRow", "CutChecked", "Written", "Skipped", "Event", "emit"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class StudyEvent(Event):
    """A record of the study itself (the CLI prints the correlations' records indented below it)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SeriesStep(StudyEvent):
    """A step of a loading series starts (``run``: computed, resumed) or is skipped (done before)."""

    stage: ClassVar[str] = "series-step"
    pair: str
    run: str

    def words(self, text):
        what = {"computed": "correlating", "resumed": "resuming", "done before": "done before, skipped:"}[self.run]
        return f"series: {what} {self.group} (scans {self.pair})"


@dataclasses.dataclass(frozen=True, kw_only=True)
class ElementSize(StudyEvent):
    """The correlations of one element size start (``pair``: which pair of a study of several)."""

    stage: ClassVar[str] = "element-size"
    element_size: int
    pair: str | None = None

    def words(self, text):
        pair = f", {self.pair} pair" if self.pair else ""
        return f"== element size {self.element_size}{pair} =="


@dataclasses.dataclass(frozen=True, kw_only=True)
class APriori(StudyEvent):
    """A sweep starts its a-priori uncertainty test."""

    stage: ClassVar[str] = "a-priori"

    def words(self, text):
        return "== a-priori uncertainty (Fourier-shifted reference) =="


@dataclasses.dataclass(frozen=True, kw_only=True)
class StepShare(StudyEvent):
    """The share ``fraction`` (0 to 1) of a long step done after ``seconds`` (a Fourier shift, a
    scan written); logged at DEBUG, as one arrives per block of the step."""

    stage: ClassVar[str] = "step-share"
    log_level: ClassVar[int] = logging.DEBUG
    step: str
    fraction: float
    seconds: float

    def words(self, text):
        return f"{self.step}: {self.fraction:4.0%} ({self.seconds:.1f} s)"


@dataclasses.dataclass(frozen=True, kw_only=True)
class UncertaintyRow(StudyEvent):
    """One element size of the a-priori test measured (its row of ``uncertainty.csv``)."""

    stage: ClassVar[str] = "uncertainty"
    row: dict

    def words(self, text):
        r = self.row
        return (f"ell {r['element_size']}: bias ({r['bias_z']:+.4f}, {r['bias_y']:+.4f}, {r['bias_x']:+.4f}) "
                f"std ({r['std_z']:.4f}, {r['std_y']:.4f}, {r['std_x']:.4f}) voxel, "
                f"delta eps {r['delta_eps']:.2e}, gap {r['final_gap_percent']:.3f}%")


@dataclasses.dataclass(frozen=True, kw_only=True)
class ResolutionRow(StudyEvent):
    """One element size of the resolution study measured (its row of ``resolution.csv``)."""

    stage: ClassVar[str] = "resolution"
    row: dict

    def words(self, text):
        r = self.row
        bound = {"=": "", "<": "< ", ">": "> "}[r["l10_bound"]]
        return (f"ell {r['element_size']}: n = {r['noise']:.4f} voxel, l10 % = {bound}{r['l10']:.1f} voxels, "
                f"MEI = {r['mei']:.3f}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class RepeatRow(StudyEvent):
    """One element size of the repeat-scan study measured (its row of ``uncertainty.csv``)."""

    stage: ClassVar[str] = "repeat"
    row: dict

    def words(self, text):
        r = self.row
        return (f"ell {r['element_size']}: spatial noise floor {r['spatial']:.4f}, temporal {r['temporal']:.4f} "
                f"voxel ({r['fields']} field(s)), bias {r['bias']:.4f}, u_rms {r['u_rms']:.4f}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class CutChecked(StudyEvent):
    """One mid-plane cut of the cut check done (``cut``: its :class:`chunkdic.analysis.crosscheck.Cut`)."""

    stage: ClassVar[str] = "cut"
    cut: Any

    def words(self, text):
        c = self.cut
        return (f"cut normal to {c.axis} at {c.axis} = {c.index}: mean {c.mean:.4f}, std {c.std:.4f}, "
                f"max {c.max:.4f} pixel, correlation length {c.correlation_length:.1f} pixel, noise floor "
                f"{c.floor:.4f} pixel (of the mean {c.floor_mean:.4f}) ({c.status})")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Written(StudyEvent):
    """A study's files written."""

    stage: ClassVar[str] = "written"
    paths: list

    def words(self, text):
        return "wrote " + ", ".join(str(p) for p in self.paths)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Skipped(StudyEvent):
    """A part of a study left out (``what``), and why."""

    stage: ClassVar[str] = "skipped"
    what: str
    reason: str

    def words(self, text):
        return f"skipped {self.what}: {self.reason}"
