"""``python -m chunkdic`` = the ``chunkdic`` command."""

import sys

from .cli.main import main

sys.exit(main())
