"""The sweep of bad inputs and faults (:mod:`bad_inputs`), one test per case.

Each case runs ``python -m chunkdic ...`` in its own copy of a small fixture and checks the
promise of ``docs/safety.md`` (exit status 2 with one ``chunkdic ...: error:`` line, nothing
changed, no leftovers; or the fault's own outcome). The sweep takes about an hour on two
cores, so these tests carry the ``sweep`` marker and the default run leaves them out::

    python -m pytest -m sweep tests/sweep              # every case
    python -m pytest -m sweep tests/sweep -k K40       # one class (or a name)

``python tests/sweep/bad_inputs.py`` runs the same cases with a summary per class, also
against another source tree (``--tree``).
"""

from __future__ import annotations

import pytest

import bad_inputs as sweep

pytestmark = pytest.mark.sweep


class _Unstarted:
    """Names the cases that need the foreign services without starting them."""

    def address(self, which: str) -> str:
        return f"<{which}>"


CASES = sweep.cases(_Unstarted())  # the same list, in the same order, as with the services


@pytest.fixture(scope="session")
def live_cases():
    """Every case, with the foreign services running."""
    s = sweep.Servers()
    yield sweep.cases(s)
    s.close()


@pytest.fixture(scope="session")
def base(tmp_path_factory):
    return sweep.make_base(tmp_path_factory.mktemp("sweep"))


@pytest.mark.parametrize("index", range(len(CASES)), ids=[f"{c.cls}-{c.name}" for c in CASES])
def test_case_meets_the_promise(index, live_cases, base, tmp_path):
    case = live_cases[index]
    assert (case.cls, case.name) == (CASES[index].cls, CASES[index].name)
    if case.mount and not sweep.can_mount():
        pytest.skip("needs unshare -m (read-only and full-disk mounts)")
    outcome = sweep.run_case(case, base, tmp_path, index)
    assert outcome.ok, outcome.why
