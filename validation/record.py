"""One record schema for every study: what was measured, on what, by which command.

A record is one JSON object::

    {"schema": 1, "study": "vs_aldvc", "title": "...",
     "commit": "9537653", "date": "2026-11-27T12:22:55+00:00",
     "machine": {"host": ..., "cores": 2, "ram_gib": 23.5, "load": [l1, l5, l15] | null},
     "versions": {"chunkdic": "0.1.0", "python": ..., "numpy": ..., ..., "al-dvc": "1.2.1"},
     "command": "python -m validation run vs_aldvc",
     "settings": {...}, "rows": [{...}, ...], "notes": "...",
     "unknown": [], "source": null}

``rows`` are flat mappings of scalars (one table row each: case, specimen, ℓ, errors,
times). ``unknown`` names the fields a converted older record could not know (they hold
``null``); ``source`` names what it was converted from. Only the latest record of each study
is kept (``validation/records/STUDY.json``, the scale runs in ``validation/scale/records/``);
older ones live in git history.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import json
import os
import platform
import socket
import subprocess
import sys
from pathlib import Path

SCHEMA = 1
#: every key of a record, in the order it is written
FIELDS = ("schema", "study", "title", "commit", "date", "machine", "versions", "command", "settings",
          "rows", "notes", "unknown", "source")
#: fields that may be null only when named in ``unknown``
KNOWABLE = ("commit", "date", "machine", "versions", "command")
#: the packages whose versions every record carries
PACKAGES = ("chunkdic", "numpy", "scipy", "dask", "distributed", "zarr", "numba")

ROOT = Path(__file__).resolve().parents[1]
RECORDS = {"validation": ROOT / "validation" / "records", "scale": ROOT / "validation" / "scale" / "records"}


def git_commit(root: Path = ROOT) -> str | None:
    """Short hash of the checkout's HEAD, with ``+`` when the tree has uncommitted changes."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+" if dirty else "")


def machine() -> dict:
    """Host name, cores, memory (GiB) and load average of this machine now."""
    try:
        ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        ram = None
    try:
        load = [round(v, 2) for v in os.getloadavg()]
    except OSError:
        load = None
    return {"host": socket.gethostname(), "cores": os.cpu_count(), "ram_gib": None if ram is None else round(ram, 2),
            "platform": platform.platform(), "load": load}


def versions(extra: dict | None = None) -> dict:
    """Python's and the main packages' versions (``None`` for one not installed), plus ``extra``."""
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    out.update(extra or {})
    return out


def new(study: str, *, title: str, rows: list[dict], command: str | None = None, settings: dict | None = None,
        notes: str = "", extra_versions: dict | None = None) -> dict:
    """A record of ``rows`` measured now, on this machine, at this checkout."""
    record = {
        "schema": SCHEMA, "study": study, "title": title, "commit": git_commit(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(), "versions": versions(extra_versions),
        "command": command or " ".join(["python"] + sys.argv), "settings": settings or {},
        "rows": rows, "notes": notes, "unknown": [], "source": None,
    }
    check(record)
    return record


def check(record: dict) -> dict:
    """Raise ``ValueError`` unless ``record`` follows the schema; return it."""
    if not isinstance(record, dict):
        raise ValueError("a record is a JSON object")
    missing = [k for k in FIELDS if k not in record]
    extra = [k for k in record if k not in FIELDS]
    if missing or extra:
        raise ValueError(f"record fields: missing {missing}, unexpected {extra}")
    if record["schema"] != SCHEMA:
        raise ValueError(f"schema {record['schema']!r}, expected {SCHEMA}")
    unknown = set(record["unknown"])
    for key in KNOWABLE:
        if record[key] is None and key not in unknown:
            raise ValueError(f"{key} is null but not listed in 'unknown'")
    if not isinstance(record["rows"], list) or not record["rows"]:
        raise ValueError("rows: a non-empty list")
    for i, row in enumerate(record["rows"]):
        if not isinstance(row, dict):
            raise ValueError(f"row {i} is not an object")
        bad = [k for k, v in row.items() if isinstance(v, (dict, list))]
        if bad:
            raise ValueError(f"row {i}: values must be scalars, not {bad}")
    return record


def path_of(study: str, folder: str = "validation") -> Path:
    """Where the latest record of ``study`` lives."""
    return RECORDS[folder] / f"{study}.json"


def write(record: dict, path: Path) -> Path:
    """Write ``record`` (checked) to ``path``, replacing the earlier one atomically."""
    check(record)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False) + "\n")
    os.replace(tmp, path)
    return path


def load(path: Path) -> dict:
    """Read and check a record."""
    return check(json.loads(Path(path).read_text()))


def all_records() -> list[Path]:
    """Every record kept (both folders)."""
    return sorted(p for folder in RECORDS.values() for p in folder.glob("*.json"))
