"""``python -m validation {list, run STUDY, convert STUDY RAW..., check}`` (see validation/README.md)."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from . import record
from .studies import HERE, STUDIES


def _fill(args, **values) -> list[str]:
    return [a.format(**values) for a in args]


def _chunkdic_cli() -> list[str]:
    exe = shutil.which("chunkdic", path=str(Path(sys.executable).parent))
    return [exe] if exe else [sys.executable, "-m", "chunkdic"]


def run(name: str, workdir: Path, extra: list[str], output: Path | None = None) -> Path:
    """Run study ``name`` in ``workdir`` and write its record (to ``output``, default the study's
    record, replacing it); return the record's path."""
    study = STUDIES[name]
    workdir.mkdir(parents=True, exist_ok=True)
    raw = workdir / f"{name}-raw.json"
    raw_name = f"validation_{name}"  # scripts that take a record name write records/bench_*_NAME.json
    values = {"workdir": str(workdir), "raw": str(raw), "raw_name": raw_name}
    for step in study.prepare:
        cmd = _fill(step, **values)
        if cmd[0] == "chunkdic":
            if Path(cmd[2]).exists():
                continue  # the scans of an earlier run
            cmd = _chunkdic_cli() + cmd[1:]
        subprocess.run(cmd, check=True)
    cmd = [sys.executable, str(study.script_path), *_fill(study.args, **values), *extra]
    subprocess.run(cmd, check=True)
    if not raw.exists():  # written beside the script under its own name
        named = study.script_path.parent / "records" / f"{study.script_path.stem}_{raw_name}.json"
        shutil.move(named, raw)
    data = json.loads(raw.read_text())
    rec = record.new(name, title=study.title, rows=study.rows(data), command=" ".join(["python -m validation run", name, *(["--", *extra] if extra else [])]),
                     settings={"script": study.script, "args": [*study.args, *extra]}, notes=study.about,
                     extra_versions=_peer_version(data))
    return record.write(rec, output or record.path_of(name, study.folder))


def _peer_version(data: dict) -> dict:
    meta = data.get("meta", {}) if isinstance(data, dict) else {}
    return {"al-dvc": meta["aldvc_version"]} if "aldvc_version" in meta else {}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m validation", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="the studies and their records")
    r = sub.add_parser("run", help="measure a study again and replace its record")
    r.add_argument("study", choices=sorted(STUDIES))
    r.add_argument("--workdir", type=Path, default=None, help="scans and runs (default: a temporary directory)")
    r.add_argument("--output", type=Path, default=None, help="write the record here (default: replace the study's)")
    p.epilog = "Arguments after -- go to the study's script, after its own (argparse keeps the last of a repeated option)."
    c = sub.add_parser("convert", help="turn the study script's own JSON files into the study's record")
    c.add_argument("study", choices=sorted(STUDIES))
    c.add_argument("raw", nargs="+", type=Path)
    sub.add_parser("check", help="check every record against the schema")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []  # more arguments for the study's script
    a = p.parse_args(argv[:len(argv) - len(extra) - (1 if "--" in argv else 0)])
    if a.command == "list":
        for s in STUDIES.values():
            path = record.path_of(s.name, s.folder)
            rec = record.load(path) if path.exists() else None
            when = f"{rec['date']} at {rec['commit']}" if rec else "no record"
            print(f"{s.name:15s} {s.folder:10s} {when:40s} {s.title}")
    elif a.command == "run":
        if a.workdir is None:
            with tempfile.TemporaryDirectory(prefix=f"validation-{a.study}-") as tmp:
                print(run(a.study, Path(tmp), extra, a.output))
        else:
            print(run(a.study, a.workdir, extra, a.output))
    elif a.command == "convert":
        from .legacy import convert

        print(convert(a.study, a.raw))
    else:
        for path in record.all_records():
            record.load(path)
            print(f"ok {path.relative_to(HERE.parent)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
