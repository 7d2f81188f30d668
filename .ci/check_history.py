"""Fail on development history written into the product: the package, its docs, the README,
the validation studies and the benchmarks.

The product speaks in the present tense about what it is; how it came to be goes into
commit messages and ``docs/changelog.md``. A line is refused when it names a development
round or an issue of this project ("session 31", "issue 20", "issue-20 cases"), marks
something "(new)", dates a fact by a round ("since session 30", "until issue 21", "before
commit ..."), says what the product "used to" do, cites an issue's "(item 3)", or describes
how a measurement was scheduled ("autogroup"). External
references keep their form: "numcodecs issue #228" (with ``#``) passes.

Usage: ``python .ci/check_history.py [ROOT]``; exit status 1 and one line per offence.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

#: what is scanned, relative to the repository's root
SCOPE = ("chunkdic", "docs", "README.md", "validation", "benchmarks")
SUFFIXES = {".py", ".pyi", ".md", ".rst", ".txt", ".yaml", ".yml", ".cff"}
#: generated or history by design
EXCLUDED = ("docs/changelog.md", "docs/_build/", "docs/gallery/", "docs/api/")

PATTERNS = [
    (re.compile(r"\b(sessions?|rounds?) ?[0-9]", re.I), "a development round"),
    # (after a "\n" escape in a string literal too: no word boundary there)
    (re.compile(r"(?:\b|(?<=\\n))issues? ?[0-9]|\bissue-[0-9]", re.I), "an issue number of this project"),
    (re.compile(r"\(new\)", re.I), "a '(new)' mark"),
    (re.compile(r"\b(since|until|before|after) (session|issue|round|commit|version)\b", re.I), "a dated fact"),
    (re.compile(r"autogroup", re.I), "how a measurement was scheduled"),
    # "it used to hang", not "the weights (that are) used to compute": a be-verb before it passes
    (re.compile(r"(?<!\bis )(?<!\bare )(?<!\bbe )(?<!\bbeen )(?<!\bwas )(?<!\bwere )(?<!\bbeing )\bused to\b", re.I),
     "what the product used to do"),
    (re.compile(r"\(items? [0-9]", re.I), "an item of an issue"),
]


def offences(root: Path) -> list[str]:
    """``path:line: why: text`` for every offending line under ``root``."""
    out = []
    for entry in SCOPE:
        base = root / entry
        files = [base] if base.is_file() else sorted(p for p in base.rglob("*") if p.suffix in SUFFIXES)
        for path in files:
            rel = path.relative_to(root).as_posix()
            if any(rel == e or rel.startswith(e) for e in EXCLUDED) or not path.is_file():
                continue
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
                for pattern, why in PATTERNS:
                    if pattern.search(line):
                        out.append(f"{rel}:{number}: {why}: {line.strip()[:160]}")
                        break
    return out


def main(argv: list[str]) -> int:
    root = Path(argv[1]) if len(argv) > 1 else Path(__file__).resolve().parents[1]
    found = offences(root)
    for line in found:
        print(line)
    if found:
        print(f"{len(found)} line(s) write history into the product: say it in the present tense, "
              "and put the history in the commit message or docs/changelog.md", file=sys.stderr)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
