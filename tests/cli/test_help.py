"""Every help text renders as written (argparse formats help strings with ``%``: a bare
``% a`` in "l10 % and MEI" printed the parser's internal dict instead)."""

from __future__ import annotations

import pytest

from chunkdic.cli.app import build_parser, main


def subcommands() -> list[str]:
    sub = next(a for a in build_parser()._actions if a.choices and isinstance(a.choices, dict))
    return sorted(sub.choices)


def test_top_level_help_lists_every_subcommand_in_plain_words(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "option_strings" not in out and "'dest'" not in out
    assert "spatial resolution l10 % and MEI" in " ".join(out.split())


@pytest.mark.parametrize("name", subcommands())
def test_each_subcommand_help_renders(name, capsys):
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: chunkdic {name}") and "option_strings" not in out
