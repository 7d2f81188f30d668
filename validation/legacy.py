"""Convert a study script's own JSON (and the older records it wrote) into the record schema.

The older records hold their date, host, cores and the script's arguments, some their commit
and load average; none holds the versions of the packages. What a record cannot know is
``null`` and named in its ``unknown`` list. Where a record names no commit, the commit that
added it to the repository stands in (the code it measured is that commit's or an earlier
one's): ``notes`` says so.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from . import record
from .studies import STUDIES

#: where the older records were kept (they stay in git history)
OLD_RECORDS = record.ROOT / "benchmarks" / "records"


def _adding_commit(path: Path) -> str | None:
    try:
        out = subprocess.run(["git", "log", "--diff-filter=A", "--format=%h", "-1", "--", str(path)],
                             cwd=record.ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return out or None


def _commit_date(commit: str | None) -> str | None:
    if commit is None:
        return None
    try:
        return subprocess.run(["git", "show", "-s", "--format=%ci", commit], cwd=record.ROOT, capture_output=True,
                              text=True, check=True).stdout.strip() or None
    except (OSError, subprocess.CalledProcessError):
        return None


def _meta(data: dict) -> dict:
    meta = data.get("meta")
    if meta is None:  # bench_large_strain.py: the arguments only
        meta = {"argv": data.get("argv", [])}
    return meta


def convert(study_name: str, raws: list[Path]) -> Path:
    """Write the record of ``study_name`` from the raw JSON files ``raws`` (oldest first)."""
    study = STUDIES[study_name]
    rows, dates, commits, machines, commands, notes = [], [], [], [], [], []
    peer = {}
    for raw in raws:
        raw = Path(raw) if Path(raw).exists() else OLD_RECORDS / raw
        data = json.loads(raw.read_text())
        meta = _meta(data)
        commit = meta.get("commit")
        if commit is None:
            commit = _adding_commit(raw)
            if commit:
                notes.append(f"{raw.name}: no commit recorded; {commit} added it")
        date = meta.get("date") or _commit_date(commit)
        these = study.rows(data)
        if len(raws) > 1:
            for row in these:
                row.setdefault("commit", commit)
                row.setdefault("date", date)
        rows += these
        dates.append(date)
        commits.append(commit)
        machines.append({"host": meta.get("host"), "cores": meta.get("cores"),
                         "ram_gib": round(meta["ram_gib"], 2) if meta.get("ram_gib") else None,
                         "platform": None, "load": [round(v, 2) for v in meta["load_start"]] if meta.get("load_start")
                         else None})
        commands.append(f"python validation/{study.script} " + " ".join(map(str, meta.get("argv", []))))
        if "aldvc_version" in meta:
            peer["al-dvc"] = meta["aldvc_version"]
    versions = {"python": None, **{name: None for name in record.PACKAGES}, "chunkdic": "0.1.0", **peer}
    unknown = [f"versions.{k}" for k, v in versions.items() if v is None]
    unknown += [f"machine.{k}" for k, v in machines[-1].items() if v is None]
    rec = {
        "schema": record.SCHEMA, "study": study.name, "title": study.title,
        "commit": commits[-1], "date": dates[-1], "machine": machines[-1],
        "versions": versions, "command": " ; ".join(commands),
        "settings": {"script": study.script, "args": list(study.args)}, "rows": rows,
        "notes": "; ".join([study.about, *notes]), "unknown": unknown,
        "source": ", ".join(Path(r).name for r in raws),
    }
    for key in ("commit", "date"):
        if rec[key] is None:
            rec["unknown"].append(key)
    return record.write(rec, record.path_of(study.name, study.folder))
