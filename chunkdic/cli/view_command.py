"""``chunkdic view``: open results, loading series or fields images in napari.

Thin over :func:`chunkdic.viewer.launch.view`. Without napari, a Qt binding or a display:
one line on stderr, exit 2 (nothing is read).
"""

from __future__ import annotations

from .common import say


def register(subparsers) -> None:
    """Add ``view`` to ``subparsers``."""
    p = subparsers.add_parser(
        "view", help="open results, loading series or fields images in napari (pip install 'chunkdic[napari]')",
        description="Open chunkdic outputs in a napari window, in the scan's physical units: the reference scan "
                    "(multiscale), the nodal displacement as vectors coloured by |U|, |U|, eps_zz, eps_eq and the "
                    "residual from an export --fields image (given with --fields, or found beside the result), "
                    "the specimen mask as labels, the nodes flagged weak (poorly textured, regularised or not "
                    "settled at the noise level) as points, their count in the layer's name; a loading series "
                    "with a time axis t (scan index). The same "
                    "layers open with 'napari RESULT' once chunkdic is installed (its npe2 reader). Exit 2 when "
                    "napari, a Qt binding or a display is missing.")
    p.add_argument("paths", nargs="+", metavar="PATH", help="result, series or fields image (Zarr groups)")
    p.add_argument("--fields", default=None, metavar="FIELDS",
                   help="fields image of the result (chunkdic export --fields; default: one found beside it)")
    p.add_argument("--no-scan", dest="scan", action="store_false", help="leave out the reference scan(s)")
    p.add_argument("--max-vectors", type=int, default=None,
                   help="most displacement vectors shown per time step (default: 4000; a stride per axis)")
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    from ..inputs import number
    from ..viewer.launch import view
    from ..viewer.layers import MAX_VECTORS

    limit = MAX_VECTORS if args.max_vectors is None else number(args.max_vectors, "--max-vectors", minimum=1,
                                                                 integer=True)
    view(args.paths, fields=args.fields, scan=args.scan, max_vectors=int(limit))
    say("napari closed")
    return 0
