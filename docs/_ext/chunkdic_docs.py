"""Sphinx extension of chunkdic's documentation: pages and tables made from the code and the records.

- ``docs/api/index.rst`` is written at each build from ``chunkdic/__init__.pyi``
  (:mod:`codefacts`): every public name gets an autosummary entry and a page;
- ``chunkdic-settings`` / ``chunkdic-config``: the configuration tables, from
  :class:`chunkdic.Settings`'s fields and the defaults and comments of ``chunkdic/config.py``;
- ``validation-table RECORD`` and ``validation-geomean RECORD``: a table of a study's latest
  record (``validation/record.py`` schema), or geometric means over its rows; a changed
  record rebuilds the page.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import defaultdict
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import Directive, directives

from codefacts import config_comments, public_names

DOCS = Path(__file__).resolve().parents[1]
ROOT = DOCS.parent


# --- the API page ---------------------------------------------------------------------------

def write_api_page(app, config=None) -> None:
    """Write ``api/index.rst``: the public names of ``chunkdic/__init__.pyi`` by section."""
    groups: dict[str, list[str]] = defaultdict(list)
    for name, section in public_names():
        groups[section].append(name)
    lines = ["API reference", "=============", "",
             "Every public name of the package (``chunkdic/__init__.pyi``), importable as ``chunkdic.NAME``.",
             "This page is written from that file at each build.", "", ".. currentmodule:: chunkdic", ""]
    for section, names in groups.items():
        lines += [section, "-" * len(section), "", ".. autosummary::", "   :toctree: generated", ""]
        lines += [f"   {n}" for n in names] + [""]
    page = DOCS / "api" / "index.rst"
    page.parent.mkdir(exist_ok=True)
    text = "\n".join(lines)
    if not page.exists() or page.read_text() != text:  # rewriting an unchanged page would rebuild it
        page.write_text(text)


# --- tables -----------------------------------------------------------------------------------

def table(headers: list[str], rows: list[list[str]], widths: list[int] | None = None) -> nodes.table:
    """A docutils table of plain-text cells."""
    tab = nodes.table(classes=["chunkdic-table"])
    group = nodes.tgroup(cols=len(headers))
    tab += group
    for w in widths or [1] * len(headers):
        group += nodes.colspec(colwidth=w)

    def row_of(cells):
        row = nodes.row()
        for cell in cells:
            entry = nodes.entry()
            entry += nodes.paragraph(text=str(cell))
            row += entry
        return row

    head = nodes.thead()
    head += row_of(headers)
    body = nodes.tbody()
    for r in rows:
        body += row_of(r)
    group += head
    group += body
    return tab


def _literal_default(value) -> str:
    return "None" if value is None else repr(value)


class SettingsTable(Directive):
    """The algorithm settings: field, command-line flag, default, choices, what it does."""

    def run(self):
        from chunkdic.method.settings import Settings

        self.state.document.settings.env.note_dependency(str(ROOT / "chunkdic" / "engine" / "settings.py"))
        rows = []
        for f in dataclasses.fields(Settings):
            meta = f.metadata
            flag = meta.get("flag") or ("--" + f.name.replace("_", "-") if meta else "(Python only)")
            if f.name == "element_size":
                flag, default, help_ = "-l, --element-size", "(required)", "element edge ℓ, voxels of the level " \
                                                                            "(or a length with its unit: 80um)"
            else:
                default, help_ = _literal_default(f.default), meta.get("help", "convergence on coarser levels "
                                                                              "(their field is only a start)")
            choices = ", ".join(meta.get("choices") or ()) if meta else ""
            rows.append([f.name, flag, default, choices, help_])
        return [table(["Settings field", "command line", "default", "choices", "what it does"], rows,
                      [14, 14, 8, 14, 40])]


class ConfigTable(Directive):
    """The runtime knobs of ``dask.config`` under ``chunkdic.``, with the comment above each."""

    def run(self):
        from chunkdic.config import DEFAULTS

        path = ROOT / "chunkdic" / "config.py"
        self.state.document.settings.env.note_dependency(str(path))
        comments = config_comments()
        rows = []
        for key, value in DEFAULTS["chunkdic"].items():
            env = "DASK_CHUNKDIC__" + key.upper().replace("-", "_")
            rows.append([f"chunkdic.{key}", env, _literal_default(value), comments.get(key, "")])
        return [table(["dask.config key", "environment variable", "default", "what it sets"], rows,
                      [16, 22, 8, 44])]


# --- validation tables ------------------------------------------------------------------------

def _format(value, spec: str) -> str:
    if value is None:
        return "–"
    if spec and isinstance(value, (int, float)) and not isinstance(value, bool):
        return format(value, spec)
    return str(value)


def _record_rows(directive: Directive) -> tuple[dict, list[dict]]:
    """The record named by the directive's argument (noted as a dependency of the page) and
    its rows that match ``:where: key=v1|v2, key2=v``."""
    path = ROOT / directive.arguments[0]
    directive.state.document.settings.env.note_dependency(str(path))
    rec = json.loads(path.read_text())
    where = [tuple(part.strip().split("=", 1)) for part in directive.options.get("where", "").split(",")
             if part.strip()]
    rows = [r for r in rec["rows"] if all(str(r.get(k)) in v.split("|") for k, v in where)]
    if not rows:
        raise directive.error(f"{directive.arguments[0]}: no row matches {where}")
    return rec, rows


class ValidationTable(Directive):
    """``.. validation-table:: validation/records/STUDY.json``, one content line per column,
    ``key | header | format``, and an optional ``:where: key=v1|v2, key2=v``."""

    required_arguments = 1
    has_content = True
    option_spec = {"where": directives.unchanged, "caption": directives.unchanged}

    def run(self):
        rec, matching = _record_rows(self)
        columns = [[part.strip() for part in line.split("|")] + ["", ""] for line in self.content if line.strip()]
        rows = [[_format(r.get(key), spec) for key, _, spec, *_ in columns] for r in matching]
        machine = rec["machine"] or {}
        about = (f"Record {self.arguments[0]}: commit {rec['commit']}, {rec['date']}, "
                 f"{machine.get('cores') or '?'} cores"
                 + (f", load {machine['load'][0]:.1f}" if machine.get("load") else "")
                 + f". Regenerate: python -m validation run {rec['study']}.")
        out = []
        if "caption" in self.options:
            out.append(nodes.paragraph(text=self.options["caption"]))
        out.append(table([c[1] for c in columns], rows))
        out.append(nodes.paragraph(text=about, classes=["chunkdic-record"]))
        return out


def _order(value):
    """Numbers in their order, before text in its own."""
    return (0, value, "") if isinstance(value, (int, float)) and not isinstance(value, bool) else (1, 0, str(value))


class ValidationGeomean(Directive):
    """``.. validation-geomean:: RECORD`` with ``:value: key``, ``:by: key1, key2`` and
    ``:where:``: the geometric mean of ``value`` over the rows of each group."""

    required_arguments = 1
    option_spec = {"value": directives.unchanged_required, "by": directives.unchanged_required,
                   "where": directives.unchanged, "header": directives.unchanged}

    def run(self):
        _, matching = _record_rows(self)
        by = [k.strip() for k in self.options["by"].split(",")]
        value = self.options["value"]
        groups: dict[tuple, list[float]] = defaultdict(list)
        for r in matching:
            if r.get(value):
                groups[tuple(r.get(k) for k in by)].append(float(r[value]))
        rows = [[*map(str, key), f"{math.exp(sum(map(math.log, v)) / len(v)):.2f}", str(len(v))]
                for key, v in sorted(groups.items(), key=lambda kv: tuple(map(_order, kv[0])))]
        header = self.options.get("header", f"geometric mean of {value}")
        return [table([*by, header, "cases"], rows)]


def setup(app):
    app.connect("config-inited", write_api_page)  # before Sphinx lists the sources and autosummary writes its stubs
    app.add_directive("chunkdic-settings", SettingsTable)
    app.add_directive("chunkdic-config", ConfigTable)
    app.add_directive("validation-table", ValidationTable)
    app.add_directive("validation-geomean", ValidationGeomean)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
