"""Run time of chunkdic settings against each other, alternated in one process (CPU seconds).

Usage::

    python validation/scale/bench_settings_time.py PAIRDIR [--ell 12] [--repeats 3] \\
        [--variant NAME[:KEY=VALUE,...]] ... [--record PATH]

``PAIRDIR`` holds ``ref.zarr`` and ``def.zarr`` (e.g. the 300³ grains band that
``bench_vs_aldvc.py --sizes 300 --cases band --specimen grains --workdir W`` writes to
``W/band-300-grains-uint16-n0.02-s1``). Each ``--variant`` is a name and the settings it
passes to :func:`chunkdic.correlate` (default: ``default`` and ``cells32:grey_cell=32``);
values are read as JSON where they parse (``grey_cell=32`` is the number 32). After a
warm-up on a 100³ ROI of the pair (Numba caches), the variants run in turn ``--repeats``
times in this process; printed per run: wall and CPU seconds (the process's, every thread:
on a shared machine the CPU time is the figure that means something), status, the
regularisation length, freed terms, Gauss–Newton passes on level 0 and the load average;
then the medians. The JSON record (``--record``) holds every run.

The generalisation of ``bench_irls_time.py`` (plain penalty against the default), used for
the brightness cells' cost at 300³ (docs/engine.md, "Brightness").
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import chunkdic


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_variant(spec: str) -> tuple[str, dict]:
    """``NAME[:KEY=VALUE,...]`` -> ``(NAME, {KEY: VALUE})``.

    >>> parse_variant("cells32:grey_cell=32,regularization_reweights=0")
    ('cells32', {'grey_cell': 32, 'regularization_reweights': 0})
    >>> parse_variant("default")
    ('default', {})
    """
    name, _, rest = spec.partition(":")
    opts = {}
    for item in filter(None, rest.split(",")):
        key, sep, val = item.partition("=")
        if not sep:
            raise SystemExit(f"bench_settings_time: bad variant item {item!r} (KEY=VALUE)")
        opts[key.strip()] = _value(val.strip())
    return name, opts


def one_run(ref: str, dfm: str, ell: int, opts: dict) -> dict:
    """One correlation: wall and CPU seconds, status, length, freed terms, level-0 passes, load."""
    t0, c0 = time.perf_counter(), time.process_time()
    res = chunkdic.correlate(ref, dfm, element_size=ell, **opts)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    reg = res.info.get("regularization") or {}
    return {"wall": wall, "cpu": cpu, "status": res.info["status"], "length": reg.get("length"),
            "freed": reg.get("freed_terms"), "passes": int((res.history["level"] == 0).sum()),
            "drift": (res.info.get("grey_level") or {}).get("drift"),
            "load": open("/proc/loadavg").read().split()[:3]}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("pair", type=Path)
    p.add_argument("--ell", type=int, default=12)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--variant", action="append", default=None, metavar="NAME[:KEY=VALUE,...]")
    p.add_argument("--record", type=Path, default=None)
    args = p.parse_args(argv)
    variants = [parse_variant(v) for v in (args.variant or ["default", "cells32:grey_cell=32"])]
    ref, dfm = str(args.pair / "ref.zarr"), str(args.pair / "def.zarr")
    chunkdic.correlate(ref, dfm, element_size=args.ell, roi="100:200,100:200,100:200")  # warm-up
    out = {"meta": {"pair": str(args.pair), "ell": args.ell, "variants": dict(variants),
                    "date": time.strftime("%Y-%m-%d %H:%M:%S")},
           "runs": {name: [] for name, _ in variants}}
    for _ in range(args.repeats):
        for name, opts in variants:
            out["runs"][name].append(one_run(ref, dfm, args.ell, opts))
            print(name, json.dumps(out["runs"][name][-1]), flush=True)
            if args.record:
                args.record.write_text(json.dumps(out, indent=1))
    for name, rows in out["runs"].items():
        print(f"{name}: median wall {statistics.median(r['wall'] for r in rows):.1f} s, "
              f"cpu {statistics.median(r['cpu'] for r in rows):.1f} s", flush=True)


if __name__ == "__main__":
    main()
