"""``python -m chunkdic`` = the ``chunkdic`` command."""

import sys

from .cli.app import main

sys.exit(main())
