"""The studies: how each is run, and how its script's output becomes the rows of a record.

Each study runs one script of ``validation/scripts/`` (accuracy) or ``validation/scale/``
(hour-long runs at 512³–2048³) with fixed arguments; the script writes its own JSON, which
:func:`Study.rows` flattens into table rows (one mapping of scalars per row). ``{workdir}``
and ``{raw}`` in the arguments are replaced by the run's work directory and the path of the
script's JSON.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

HERE = Path(__file__).resolve().parent


def _vs_aldvc_rows(raw: dict) -> list[dict]:
    """One row per case, specimen and ℓ: both tools scored between the nodes on their common voxels
    (σ pooled for the translation ``noise``, the RMS vector error otherwise)."""
    rows = []
    for r in raw["results"]:
        case, _, specimen = r["case"].partition("/")
        c, a = r["chunkdic"], r.get("al-dvc")
        metric = "sigma" if case in ("noise", "shift") else "rms"
        mine = c.get(f"{metric}_common") if a else c.get(metric)
        theirs = a.get(f"{metric}_common") if a else None
        rows.append({
            "case": case, "specimen": specimen or r.get("specimen"), "size": r["shape"][0], "ell": r["ell"],
            "metric": metric, "chunkdic": mine, "aldvc": theirs,
            "ratio": mine / theirs if (a and theirs) else None,
            "status": c.get("status"), "reg_length": c.get("reg_length"),
            "chunkdic_wall_s": c.get("wall"), "aldvc_wall_s": a.get("wall") if a else None,
            "chunkdic_cpu_s": c.get("proc_cpu"), "aldvc_cpu_s": a.get("proc_cpu") if a else None,
            "chunkdic_peak_gb": c["peak_rss_mb"] / 1024 if c.get("peak_rss_mb") else None,
            "aldvc_peak_gb": a["peak_rss_mb"] / 1024 if a and a.get("peak_rss_mb") else None,
            "aldvc_status": a.get("status") if a else None,
        })
    return rows


def _texture_rows(raw: dict) -> list[dict]:
    """:func:`_vs_aldvc_rows` with the texture scale (``concrete-ts2``: concrete at 2) and the oracle:
    the least error of the candidate lengths ``ℓ·2^(k/2)`` (their linearised fields, scored on the
    voxels both tools score) and its length."""
    rows = _vs_aldvc_rows(raw)
    for row, r in zip(rows, raw["results"]):
        specimen, _, scale = row["specimen"].partition("-ts")
        c, metric = r["chunkdic"], row["metric"]
        oracle = c.get(f"oracle_{metric}_common", c.get(f"oracle_{metric}"))
        row.update(specimen=specimen, texture_scale=float(scale or 1), oracle=oracle,
                   oracle_length=c.get("oracle_length"),
                   over_oracle=row["chunkdic"] / oracle if (oracle and row["chunkdic"]) else None)
    return rows


def _offset_rows(raw: dict) -> list[dict]:
    """:func:`_texture_rows` with the feature's offset along z from the volume's centre (voxels)
    and each tool's grid floor: its node grid holding the true field, scored the same way."""
    rows = _texture_rows(raw)
    for row, r in zip(rows, raw["results"]):
        c, a = r["chunkdic"], r.get("al-dvc") or {}
        row.update(offset=float(r.get("offset", 0.0)), chunkdic_floor=c.get("floor_common"),
                   aldvc_floor=a.get("floor_common"))
    return rows


def _texture_scales_rows(raw: dict) -> list[dict]:
    """One row per specimen, texture scale and ℓ: the autocorrelation length per axis and the
    per-element mean squared gradient's median, 10 % quantile over the median, and the fraction
    of elements below a tenth of the median."""
    rows = []
    for r in raw["rows"]:
        acl = r["acl"]
        for ell, g in r["gradient"].items():
            rows.append({"specimen": r["specimen"], "texture_scale": r["scale"], "size": r["size"],
                         "acl_z": acl[0], "acl_y": acl[1], "acl_x": acl[2], "ell": int(ell),
                         "median": g["median"], "q10_over_median": g["q10_over_median"],
                         "below_tenth": g["below_tenth_of_median"]})
    return rows


def _resolution_rows(raw: dict) -> list[dict]:
    keep = ("specimen", "ell", "seed", "tool", "setting", "l10", "l10_bound", "n", "mei", "mei3d",
            "status_star", "status_translated")
    return [{k: r.get(k) for k in keep} for r in raw["rows"]]


def _texture_resolution_rows(raw: dict) -> list[dict]:
    """:func:`_resolution_rows` with the texture scale (``concrete-ts2``: concrete at 2) and
    al-dvc's MEI over chunkdic's beside each chunkdic row."""
    rows = _resolution_rows(raw)
    peers = {(r["specimen"], r["ell"], r["seed"]): r for r in rows if r["tool"] == "al-dvc"}
    for row in rows:
        peer = peers.get((row["specimen"], row["ell"], row["seed"]))
        specimen, _, scale = row["specimen"].partition("-ts")
        row.update(specimen=specimen, texture_scale=float(scale or 1),
                   mei_ratio=peer["mei"] / row["mei"] if peer and peer is not row and peer["mei"] and row["mei"]
                   else None)
    return rows


def _large_strain_rows(raw: dict) -> list[dict]:
    """chunkdic's rows, each beside al-dvc's on the same case, specimen and ℓ (rows with ``tool``)."""
    key = lambda r: (r["case"], r["specimen"], r["ell"])  # noqa: E731
    peers = {key(r): r for r in raw["rows"] if r.get("tool") == "al-dvc"}
    rows = []
    for r in raw["rows"]:
        if r.get("tool", "chunkdic") != "chunkdic":
            continue
        peer = peers.get(key(r), {})
        rows.append({"case": r["case"], "specimen": r["specimen"], "ell": r["ell"], "status": r["status"],
                     "rms": r["rms"], "max": r["max"], "reg_length": r.get("reg_length"), "wall_s": r.get("wall"),
                     "levels": " → ".join(str(v) for v in r.get("levels", [])),
                     "aldvc_rms": peer.get("rms"), "aldvc_status": peer.get("status"),
                     "ratio": r["rms"] / peer["rms"] if peer.get("rms") else None})
    return rows


def _cracks_rows(raw: dict) -> list[dict]:
    """One row per pair, texture and setting, as the script scores it (the truth beside)."""
    keep = ("pair", "texture", "regularization", "length", "status", "cracks", "detected", "tp", "fp", "recall",
            "opening", "true_opening", "sliding", "true_sliding", "sigma", "residual_ratio", "seconds")
    return [{k: r.get(k) for k in keep} for r in raw["rows"]]


def _scale_rows(raw: dict) -> list[dict]:
    meta, corr, err = raw["meta"], raw["correlate"], raw["error"]
    stage = {s["stage"]: s for s in raw["stages"]}
    c = stage["correlate"]
    roi = corr.get("roi_level0")
    return [{
        "size": roi[0][1] - roi[0][0] + 2 * roi[0][0] if roi else None,
        "roi_gvoxel": math.prod(b - a for a, b in roi) / 1e9 if roi else None, "nodes": corr["nodes"],
        "status": corr["status"], "correlate_min": c["wall_s"] / 60, "cpu_s": c["user_s"] + c["sys_s"],
        "peak_gib": c["peak_rss_gib"], "mvoxel_s_core": corr.get("mvoxel_per_s_per_core"),
        "pass_median_s": corr.get("pass_median_s"), "read_gb": c["read_chars_gb"], "written_gb": c["write_chars_gb"],
        "rms": err["rms"], "max": err["max_error"], "load_start": meta["load_start"][0],
        "load_end": meta["load_end"][0], "commit": meta.get("commit"), "date": meta.get("date"),
    }]


def _cg_scaling_rows(raw: dict) -> list[dict]:
    """One row per mesh, node blocks and workers: the medians over the repeats (their spread
    and the load beside)."""
    rows = []
    for r in raw["rows"]:
        t = [run["seconds_per_iteration"] for run in r["runs"]]
        rows.append({k: r[k] for k in ("size", "nodes", "node_blocks", "workers", "iterations", "seconds_per_iteration",
                                       "bytes_per_iteration", "tasks_per_iteration")}
                    | {"sent_mib_per_iteration": r["bytes_per_iteration"] / 2**20,
                       "node_block_elements": r["node_block_elements"], "repeats": len(t),
                       "seconds_min": min(t), "seconds_max": max(t), "load": r["load"][0]})
    return rows


def _speed_rows(raw: dict) -> list[dict]:
    rows = _vs_aldvc_rows(raw)
    for row in rows:
        row["size"] = raw["results"][0]["shape"][0]
        row["faster"] = row["aldvc_wall_s"] / row["chunkdic_wall_s"]
        row["date"] = raw["meta"]["date"]
    return rows


@dataclass(frozen=True)
class Study:
    """One study: its script, the arguments that reproduce its record, and the rows adapter."""

    name: str
    title: str
    folder: str  # "validation" or "scale"
    script: str  # path relative to validation/
    args: tuple[str, ...]
    rows: Callable[[dict], list[dict]]
    #: commands run before the script (each a tuple of arguments; ``chunkdic`` is the CLI)
    prepare: tuple[tuple[str, ...], ...] = ()
    #: the raw JSON files of the latest measurement, converted by ``python -m validation convert``
    legacy: tuple[str, ...] = field(default=())
    about: str = ""

    @property
    def script_path(self) -> Path:
        return HERE / self.script


ALDVC_100 = ("--sizes", "100", "--cases", "wave24", "wave32", "wave48", "wave64", "slip", "band", "comp10",
             "comp20", "rot10", "noise", "--specimen", "grains", "concrete", "--spacings", "8", "12", "16",
             "--solo-spacings", "6", "--repeats", "1", "--threads", "2", "--workdir", "{workdir}",
             "--record", "{raw}")

STUDIES = {s.name: s for s in (
    Study("vs_aldvc", "Accuracy against al-dvc at 100³: heterogeneous fields, between the nodes", "validation",
          "scripts/bench_vs_aldvc.py", ALDVC_100, _vs_aldvc_rows,
          legacy=("bench_vs_aldvc_100_session30.json",),
          about="both tools with their defaults, 2 threads, CT-like grains and concrete, noise 0.02 per scan"),
    Study("texture", "Three texture scales: the automatic length, the best fixed length and al-dvc", "validation",
          "scripts/bench_vs_aldvc.py",
          ("--sizes", "100", "--cases", "noise", "heterogeneous", "crack", "large", "--specimen", "grains",
           "concrete", "--texture-scales", "1", "2", "4", "--spacings", "16", "12", "8", "--solo-spacings", "6", "4",
           "--threads", "2", "--oracle", "--workdir", "{workdir}", "--record", "{raw}"), _texture_rows,
          about="100³ grains and concrete at texture scales 1, 2, 4 (autocorrelation length about 6, 12 and "
                "16–23 voxels), noise 0.02 per scan; errors between the nodes on the voxels both tools score "
                "(chunkdic's own at ℓ = 6 and 4); the oracle is the least error of the linearised fields of the "
                "candidate lengths ℓ·2^(k/2)"),
    Study("texture_large", "Large deformations on coarse textures, and a feature under one: the automatic length, "
          "the best fixed length and al-dvc", "validation", "scripts/bench_vs_aldvc.py",
          ("--sizes", "100", "--cases", "comp10", "comp20", "composed", "--specimen", "grains", "concrete",
           "--texture-scales", "2", "4", "--spacings", "16", "12", "8", "--solo-spacings", "6", "4", "--threads", "2",
           "--oracle", "--workdir", "{workdir}", "--record", "{raw}"), _texture_rows,
          about="100³ grains and concrete at texture scales 2 and 4 (autocorrelation length about 12 and 23 "
                "voxels), noise 0.02 per scan: 10 % and 20 % compression, and a crack or a slip then 10 % "
                "compression; errors between the nodes on the voxels both tools score (chunkdic's own at ℓ = 6 "
                "and 4); the oracle as in the texture study"),
    Study("feature_offsets", "Sharp features between the nodes: the crack, band and slip at four offsets, ℓ = 8",
          "validation", "scripts/bench_vs_aldvc.py",
          ("--sizes", "100", "--cases", "crack", "band", "slip", "--specimen", "concrete", "grains",
           "--texture-scales", "1", "2", "4", "--spacings", "8", "--feature-offset", "0", "2", "4", "6",
           "--threads", "2", "--oracle", "--workdir", "{workdir}", "--record", "{raw}"), _offset_rows,
          about="100³ concrete and grains at texture scales 1, 2, 4, noise 0.02 per scan, ℓ = 8; the feature's "
                "plane moved along z by 0, 2, 4 and 6 voxels from the volume's centre, which is a node plane of "
                "chunkdic's mesh and half a voxel from the midplane between two of al-dvc's (offset 4: the reverse); "
                "errors between the nodes on the voxels both tools score; the grid floor is each tool's node "
                "grid holding the true field"),
    Study("texture_resolution", "Spatial resolution and MEI on the star at three texture scales, against al-dvc",
          "validation", "scripts/bench_star_vs_aldvc.py",
          ("--specimen", "concrete", "grains", "--texture-scales", "1", "2", "4", "--spacings", "8",
           "--regularizations", "tikhonov", "--seed", "1", "--threads", "2", "--workdir", "{workdir}", "--record",
           "{raw}"),
          _texture_resolution_rows,
          about="96×240×96 concrete and grains at texture scales 1, 2, 4, noise 0.02 per scan, ℓ = 8: l10 % on "
                "the star, the noise n of a translation at the star's setting, MEI = n · l10 %"),
    Study("texture_scales", "The CT specimens' texture at each texture scale", "validation",
          "scripts/texture_scales.py",
          ("--size", "192", "--specimens", "grains", "concrete", "--scales", "1", "2", "4", "5", "--workdir",
           "{workdir}", "--json", "{raw}"), _texture_scales_rows,
          legacy=("texture_scales_192.json",),
          about="192³ reference scans, seed 1, noise 0.02; the whole scan's 3-D FFT; |∇f|² by centred differences"),
    Study("resolution", "Spatial resolution (l10 %) and MEI on the star, against al-dvc", "validation",
          "scripts/bench_star_vs_aldvc.py",
          ("--specimen", "grains", "concrete", "--spacings", "8", "--regularizations", "tikhonov", "--seed", "1",
           "--threads", "2", "--workdir", "{workdir}", "--record", "{raw}"), _resolution_rows,
          legacy=("bench_star_vs_aldvc_96x240x96_session32_l8_seed1.json",
                  "bench_star_vs_aldvc_96x240x96_session32_l8_seed2.json"),
          about="96×240×96 star, ℓ = 8, seeds 1 and 2 (the legacy record; `run` measures seed 1)"),
    Study("large_strain", "Large strain and rotation at ℓ = 8, against al-dvc", "validation",
          "scripts/bench_large_strain.py",
          ("--size", "100", "--cases", "comp10", "comp20", "rot10", "bigband", "--spacings", "8", "--aldvc",
           "--record", "{raw_name}"), _large_strain_rows,
          legacy=("bench_large_strain_vs_aldvc_l8.json",),
          about="100³ grains and concrete, noise 0.02 per scan; errors between the nodes"),
    Study("cracks", "Crack detection and opening on synthetic cracks: true and false positives", "validation",
          "scripts/bench_cracks.py",
          ("--workdir", "{workdir}", "--size", "64", "--textures", "foam", "grains", "--record", "{raw}"),
          _cracks_rows, legacy=("bench_cracks.json",),
          about="64³ pairs, planar cracks of 0.1, 0.3 and 1 voxel and crack-free fields, foam and grains, "
                "ℓ = 8 with the defaults and without regularisation"),
    Study("speed_vs_aldvc", "Time against al-dvc at 300³, 512³ and 1024³ (grains, compression band)", "scale",
          "scripts/bench_vs_aldvc.py",
          ("--sizes", "--pair", "{workdir}/grains1024", "--spacings", "16", "--points", "4000000", "--repeats", "1",
           "--threads", "2", "--workdir", "{workdir}/runs", "--record", "{raw}"), _speed_rows,
          prepare=(("chunkdic", "synth", "{workdir}/grains1024", "--shape", "1024", "--specimen", "grains",
                    "--imaging", "local", "--field", "band", "--strain", "-0.05", "--noise", "0.02"),),
          legacy=("bench_vs_aldvc_300_band_session32_sums.json", "bench_vs_aldvc_512_grains_band_session32.json",
                  "bench_vs_aldvc_1024_grains_band_session32_one_run.json"),
          about="an idle 2-core machine, both tools interleaved; `run` measures the 1024³ row"),
    Study("scale", "Full resolution end to end: 512³, 1024³, 2048³ at level 0, ℓ = 16", "scale",
          "scale/bench_stages.py",
          ("{workdir}/grains2048", "-l", "16", "--level", "0", "--workdir", "{workdir}/run", "--fields-level", "2",
           "--record", "{raw}"), _scale_rows,
          prepare=(("chunkdic", "synth", "{workdir}/grains2048", "--shape", "2048", "--specimen", "grains",
                    "--imaging", "local", "--field", "band", "--strain", "-0.05", "--noise", "0.02"),),
          legacy=("bench_stages_512_session27.json", "bench_stages_1024_session28.json",
                  "bench_stages_2048_idle_session28.json"),
          about="the CLI's defaults (embedded scheduler, CT defaults), grains pair with the band (−5 %)"),
    Study("cg_scaling", "The partitioned CG on a LocalCluster of 1, 2 and 4 workers: time, bytes and tasks per "
          "iteration", "scale", "scale/bench_cg_scaling.py", ("measure", "--record", "{raw}"), _cg_scaling_rows,
          about="bench_client_memory.py --element-size 8 --regularize 2 --solves 1 --mesh-data blocks: the solve "
                "alone, stand-in M, medians of 3 fresh processes under nice -n 10 on the shared 2-core machine"),
)}
