"""The side-by-side table from ``bench_vs_aldvc.py`` records: ratios, geometric means, targets.

Usage::

    python validation/scripts/table_vs_aldvc.py RECORD [--variant NAME=RECORD] [--before RECORD]

``RECORD`` is a ``bench_vs_aldvc.py`` record (both tools); each ``--variant`` another
record of chunkdic on the same cases (e.g. run with ``--set grey_cell=32``; its al-dvc
runs, if any, are not used: the ratios divide by ``RECORD``'s al-dvc, which is the same
from run to run on the same scans); ``--before`` an earlier record whose ratio is shown
beside. Printed, in Markdown: per case, specimen and ℓ, the between-node error on the voxels
common to both tools (RMS; σ for the translation ``noise``; over all of chunkdic's voxels
at least ℓ from the faces where al-dvc was not run) of chunkdic and of each variant, al-dvc's, the ratios chunkdic / al-dvc, the status and the regularisation length;
then the geometric mean of the ratio over the six heterogeneous fields (four waves, slip,
band) per specimen and ℓ; then the ℓ = 8 targets (≤ 0.7 on every heterogeneous
field, ≤ 1 on the large-strain ones) with the cases that miss them.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

HETEROGENEOUS = ("wave24", "wave32", "wave48", "wave64", "slip", "band")
LARGE = ("comp10", "comp20", "rot10")
ORDER = HETEROGENEOUS + LARGE + ("noise",)
LABELS = {"wave24": "wave T = 24", "wave32": "wave T = 32", "wave48": "wave T = 48", "wave64": "wave T = 64",
          "slip": "slip", "band": "band −8 %", "comp10": "−10 % compression", "comp20": "−20 % compression",
          "rot10": "10° about z", "noise": "translation (σ)"}


def load(path) -> dict:
    """``{(case, specimen, ell): result}`` of a record."""
    out = {}
    for r in json.loads(Path(path).read_text())["results"]:
        case, specimen = r["case"].split("/")
        out[(case, specimen, int(r["ell"]))] = r
    return out


def error(result: dict | None, tool: str, case: str, common: bool = True):
    """The tool's between-node error (σ for the translation), on the common voxels or all its own."""
    if result is None or not result.get(tool):
        return None
    key = "sigma" if case in ("noise", "shift") else "rms"
    v = result[tool].get(f"{key}_common" if common else key)
    return v if v is not None and math.isfinite(v) else None


def ratio(result: dict | None, peer: dict | None, case: str):
    c, a = error(result, "chunkdic", case), error(peer, "al-dvc", case)
    return c / a if c is not None and a else None


def _f(v, spec=".4f"):
    return "–" if v is None else format(v, spec)


def geomean(values):
    values = [v for v in values if v is not None]
    return math.exp(sum(map(math.log, values)) / len(values)) if values else None


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("record")
    p.add_argument("--variant", action="append", default=[], metavar="NAME=RECORD")
    p.add_argument("--before", default=None)
    args = p.parse_args(argv)
    base = load(args.record)
    variants = [(name, load(path)) for name, path in (v.split("=", 1) for v in args.variant)]
    before = load(args.before) if args.before else None
    keys = sorted(base, key=lambda k: (ORDER.index(k[0]) if k[0] in ORDER else 99, k[1] != "grains", -k[2]))
    head = ["case", "specimen", "ℓ", "chunkdic", "al-dvc", "ratio"]
    for name, _ in variants:
        head += [f"chunkdic {name}", f"ratio {name}"]
    head += ["ratio before"] if before else []
    head += ["chunkdic all voxels", "status", "ℓ_reg"] + [f"status, ℓ_reg {name}" for name, _ in variants]
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for key in keys:
        case, specimen, ell = key
        r = base[key]
        common = bool(r.get("al-dvc"))  # chunkdic alone (a solo spacing): over all its voxels
        row = [LABELS.get(case, case), specimen, str(ell), _f(error(r, "chunkdic", case, common)),
               _f(error(r, "al-dvc", case)), _f(ratio(r, r, case), ".2f")]
        for _, v in variants:
            row += [_f(error(v.get(key), "chunkdic", case, common)), _f(ratio(v.get(key), r, case), ".2f")]
        if before:
            row += [_f(ratio(before.get(key), before.get(key), case), ".2f")]
        row += [_f(error(r, "chunkdic", case, common=False)), r["chunkdic"].get("status", "–"),
                _f(r["chunkdic"].get("reg_length"), ".0f")]
        for _, v in variants:
            c = (v.get(key) or {}).get("chunkdic") or {}
            row += [f"{c.get('status', '–')}, {_f(c.get('reg_length'), '.0f')}"]
        print("| " + " | ".join(row) + " |")
    for name, v in variants:  # al-dvc is deterministic: its runs in a variant's record must be the base's
        diffs = [abs(error(v[k], "al-dvc", k[0]) / error(base[k], "al-dvc", k[0]) - 1) for k in v
                 if k in base and error(v[k], "al-dvc", k[0]) and error(base[k], "al-dvc", k[0])]
        if diffs:
            print(f"\nal-dvc in {name}'s record: {len(diffs)} runs, largest relative difference from "
                  f"the base record's {max(diffs):.1e}")
    print("\nGeometric mean of the ratio over the six heterogeneous fields:")
    for specimen in sorted({k[1] for k in base}, key=lambda s: s != "grains"):
        for ell in sorted({k[2] for k in base if base[k].get("al-dvc")}, reverse=True):
            ks = [(c, specimen, ell) for c in HETEROGENEOUS]
            line = f"- {specimen}, ℓ = {ell}: {_f(geomean(ratio(base.get(k), base.get(k), k[0]) for k in ks), '.2f')}"
            for name, v in variants:
                line += f", {name} {_f(geomean(ratio(v.get(k), base.get(k), k[0]) for k in ks), '.2f')}"
            if before:
                line += f" (before {_f(geomean(ratio(before.get(k), before.get(k), k[0]) for k in ks), '.2f')})"
            print(line)
    print("\nThe ℓ = 8 targets (≤ 0.7 heterogeneous, ≤ 1 large strain), the misses:")
    for name, rec in [("default", base)] + variants:
        misses = []
        for (case, specimen, ell) in keys:
            if ell != 8 or case not in HETEROGENEOUS + LARGE:
                continue
            q = ratio(rec.get((case, specimen, ell)), base[(case, specimen, ell)], case)
            if q is None or q > (0.7 if case in HETEROGENEOUS else 1.0):
                misses.append(f"{case}/{specimen} {_f(q, '.2f')}")
        print(f"- {name}: {', '.join(misses) if misses else 'none'}")


if __name__ == "__main__":
    main()
