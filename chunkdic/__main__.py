"""``python -m chunkdic`` = the ``chunkdic`` command."""

import sys

from .cli import main

sys.exit(main())
