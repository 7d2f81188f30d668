"""The same command line again on its own complete output: nothing to do, exit 0.

``correlate``, ``series`` and ``pyramid`` know their outputs by their fingerprints, and
``ingest``, ``export`` and ``cutcheck`` digest what shapes theirs (:mod:`chunkdic.io.madeof`).
The other commands that write one output (:data:`OUTPUTS`) are judged here from their
command line: a digest of the command, its options (but those that do not shape the
output: verbosity, scheduler, ``--overwrite``) and the identity of every input it names
(the listing of each existing path given, and of the scans a result given records), declared
for the output while the command runs (:func:`chunkdic.io.madeof.making`) and recorded
there at the commit. Run again with the same digest on its complete output, the command
says so and writes nothing; any other option or a changed input is the usual refusal of a
complete output (or its rewrite with ``--overwrite``).
"""

from __future__ import annotations

import argparse
import contextlib
import os

from ..io.jsonfile import json_dict, read_json_object
from ..io.madeof import already_made, made_of, making
from .common import say

__all__ = ["OUTPUTS", "command_digest", "judged_run"]

#: command → (the argument naming its output, the output's kind, :data:`chunkdic.io.kinds.KINDS`)
OUTPUTS = {"mask": ("output", "mask"), "synth": ("out_dir", "synth"), "table": ("output", "table"),
           "report": ("output", "figures"), "gauge": ("output", "gauge"), "crack": ("output", "cracks"),
           "uncertainty": ("output", "uncertainty"), "sweep": ("output", "sweep"),
           "resolution": ("output", "resolution"), "demo": ("directory", "demo")}
#: arguments that do not shape an output
_UNSHAPING = {"func", "command", "verbosity", "overwrite", "scheduler"}


def command_digest(args: argparse.Namespace, output: str) -> str:
    """The digest of the command line ``args`` (parsed) writing ``output``."""
    options = {k: v for k, v in sorted(vars(args).items()) if k not in _UNSHAPING and k != OUTPUTS[args.command][0]}
    given = [v for value in options.values() for v in (value if isinstance(value, (list, tuple)) else [value])]
    inputs = [v for v in given if isinstance(v, (str, os.PathLike)) and os.path.lexists(v)
              and os.path.realpath(v) != os.path.realpath(output)]
    return made_of(args.command, inputs + _recorded_scans(inputs), options)


def _recorded_scans(inputs) -> list[str]:
    """The scans that the results among ``inputs`` record as theirs (what a report or a crack
    search reads besides the result)."""
    scans = []
    for path in inputs:
        try:
            attrs = json_dict(read_json_object(os.path.join(path, "zarr.json")).get("attributes") or {})
            recorded = json_dict(json_dict(attrs.get("chunkdic") or {}).get("inputs") or {})
        except (OSError, ValueError):
            continue
        scans += [v for v in recorded.values() if isinstance(v, str) and os.path.lexists(v)]
    return scans


@contextlib.contextmanager
def judged_run(args: argparse.Namespace):
    """Around a command: yields True when its output is already its own complete one (nothing
    to do, said here); else declares the digest for the output while the command runs."""
    name, kind = OUTPUTS.get(getattr(args, "command", None), (None, None))
    output = getattr(args, name, None) if name else None
    if output is None or getattr(args, "overwrite", False):
        yield False
        return
    digest = command_digest(args, output)
    if already_made(output, kind, digest):
        say(f"{output}: already complete (the same command, options and inputs): nothing to do")
        yield True
        return
    with making(output, digest):
        yield False
