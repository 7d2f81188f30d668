"""The public names of ``chunkdic/__init__.pyi``, read without importing Sphinx or chunkdic.

The API page is written from this list (``chunkdic_docs``), and ``tests/test_docs.py``
checks it against ``chunkdic.__all__``: a name added to the face appears in the reference.
"""

from __future__ import annotations

import ast
from pathlib import Path

STUB = Path(__file__).resolve().parents[2] / "chunkdic" / "__init__.pyi"

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
