"""What the documentation reads from the code, without importing Sphinx or chunkdic.

The public names of ``chunkdic/__init__.pyi`` (the API page is written from them) and the
comment above each knob of ``chunkdic/config.py`` (the configuration table);
``tests/test_docs.py`` checks both against the package: a name added to the face appears
in the reference, a knob added to the configuration appears in its table.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "chunkdic"
STUB = PACKAGE / "__init__.pyi"
CONFIG = PACKAGE / "config.py"

#: section titles of the API page, by the subpackage a name comes from
SECTIONS = {
    "engine": "Correlation", "mesh": "Correlation", "errors": "Correlation", "solve": "Correlation",
    "results": "Results and strain",
    "analysis": "Analyses: uncertainty, resolution, sweeps, series",
    "io": "Scans: ingest, pyramid, masks",
    "views": "Figures and exports",
    "": "Package",
}


def public_names(stub: Path = STUB) -> list[tuple[str, str]]:
    """``(name, section)`` of every public name of the stub, in its order (dunders left out)."""
    tree = ast.parse(stub.read_text())
    out = []
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            top = (node.module or "").split(".")[0]
            out += [(a.asname or a.name, SECTIONS.get(top, "Package")) for a in node.names]
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("__"):
            out.append((node.name, SECTIONS[""]))
    return out


def config_comments(path: Path = CONFIG) -> dict[str, str]:
    """The comment lines right above each ``"key": value`` line of ``config.py``, by key."""
    out, pending = {}, []
    for line in path.read_text().splitlines():
        text = line.strip()
        key = re.match(r'"([a-z-]+)":\s*([^{\s])', text)  # a knob, not the namespace's opening brace
        if text.startswith("#"):
            pending.append(text.lstrip("# "))
        elif key:
            out[key.group(1)] = " ".join(pending)
            pending = []
        else:
            pending = []
    return out
