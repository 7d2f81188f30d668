"""The documentation and the evidence stay true to the code: the API page lists every public
name, the configuration table every knob, every validation record follows the one schema,
and no line of the product writes development history (``.ci/check_history.py``)."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


codefacts = _load("codefacts", ROOT / "docs" / "_ext" / "codefacts.py")
history = _load("check_history", ROOT / ".ci" / "check_history.py")
sys.path.insert(0, str(ROOT))
from validation import record  # noqa: E402


def test_api_page_names_every_public_name_of_the_package():
    import chunkdic

    listed = [name for name, _ in codefacts.public_names()]
    assert len(listed) == len(set(listed))
    assert set(listed) == set(chunkdic.__all__)


def test_configuration_table_has_a_description_for_every_knob():
    from chunkdic.config import DEFAULTS

    comments = codefacts.config_comments()
    assert set(comments) == set(DEFAULTS["chunkdic"])
    assert all(len(text) > 20 for text in comments.values())


def test_every_validation_record_follows_the_schema_and_names_its_commit():
    paths = record.all_records()
    assert {p.stem for p in paths} >= {"vs_aldvc", "resolution", "large_strain", "scale", "speed_vs_aldvc"}
    for path in paths:
        rec = record.load(path)
        assert rec["commit"], path
        assert rec["study"] == path.stem


def test_a_record_without_its_commit_is_refused_unless_it_says_so():
    rec = record.new("demo", title="t", rows=[{"case": "a", "rms": 0.1}], command="python -m validation run demo")
    assert rec["versions"]["numpy"] and rec["machine"]["cores"]
    broken = dict(rec, commit=None)
    with pytest.raises(ValueError, match="commit"):
        record.check(broken)
    record.check(dict(broken, unknown=["commit"]))
    with pytest.raises(ValueError, match="scalars"):
        record.check(dict(rec, rows=[{"case": [1, 2]}]))
    json.dumps(rec)  # JSON-able as written


def test_the_product_writes_no_history():
    assert history.offences(ROOT) == []


def test_the_history_check_finds_each_form_and_spares_external_references(tmp_path):
    (tmp_path / "chunkdic").mkdir()
    (tmp_path / "docs").mkdir()
    lines = ["x = 1  # measured in session 31", "the cases of issue 20 pass", "the issue-20 cases",
             "## Masks (new)", "faster since version 2", "at autogroup nice 19", "local:0 used to hang",
             "- **Names in figures** (item 3): report --label", r'print("\nIssue 20 targets")']
    clean = ["a cut Blosc frame (numcodecs issue #228)", "the penalty, since it damps short waves",
             "the weights are used to sum", "what was used to build it", "items 2 and 3 of the list"]
    (tmp_path / "chunkdic" / "mod.py").write_text("\n".join(lines + clean) + "\n")
    (tmp_path / "docs" / "changelog.md").write_text("## session 31: what changed\n")
    (tmp_path / "README.md").write_text("fine\n")
    found = history.offences(tmp_path)
    assert [line.split(":")[1] for line in found] == [str(i) for i in range(1, len(lines) + 1)]


#: a citation of a section: the page's path under docs/, a comma and the section's name in double
#: quotes in code; a Markdown link, then the name in parentheses and quotes, in the docs
_CODE_CITATION = re.compile(r'(docs/[\w/.-]+\.md)(?:,|\s*\(|\s*:)?\s*"([^"\n]+)"')
_DOC_CITATION = re.compile(r'\]\(([^)#]+\.md)\),?\s*\(?"([^"\n]+)"')


def _section_names(doc: Path) -> set[str]:
    """Headings and bold paragraph leads (``**The least error in voxels**``) of a Markdown page."""
    text = doc.read_text(encoding="utf-8")
    names = {m.group(1).strip() for m in re.finditer(r"^#+\s+(.+)$", text, re.M)}
    return names | {m.group(1).strip().rstrip(".:").strip() for m in re.finditer(r"\*\*([^*\n]+?)\*\*", text)}


def _citations():
    for base in ("chunkdic", "validation", "tests", "benchmarks", "docs"):
        for path in sorted((ROOT / base).rglob("*")):
            if path.suffix not in (".py", ".md") or "_build" in path.parts:
                continue
            for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
                for m in _CODE_CITATION.finditer(line):
                    yield path, number, ROOT / m.group(1), m.group(2).strip()
                for m in _DOC_CITATION.finditer(line):
                    yield path, number, (path.parent / m.group(1)).resolve(), m.group(2).strip()


def test_every_cited_section_of_the_docs_exists():
    # a comment or docstring that sends the reader to a section of a page must find it there: a
    # heading, or a bold paragraph lead, that begins with the name
    cited, missing, names = 0, [], {}
    for path, number, doc, name in _citations():
        cited += 1
        if doc.exists() and doc not in names:
            names[doc] = _section_names(doc)
        if not any(n.startswith(name) for n in names.get(doc, ())):
            missing.append(f"{path.relative_to(ROOT)}:{number}: {doc.name}, {name!r}")
    assert cited > 50  # the pattern still reads the citations
    assert missing == []
