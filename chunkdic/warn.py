"""Warnings attributed to the user's code: the first frame outside chunkdic.

A warning is about the call the user made (``chunkdic.correlate(...)`` in their script), not
about the line inside the package that noticed it; its filename and line number are what
Python prints and what warning filters match on ``module``. A fixed ``stacklevel`` names the
right frame only for one call path, and the same check runs under several (the API, the
CLI, a sweep), so the frames are counted at the moment of the warning.
"""

from __future__ import annotations

import os
import sys
import warnings

__all__ = ["warn_user"]

#: the package's directory: frames whose code lies under it are chunkdic's
PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn_user(message: str, category: type[Warning]) -> None:
    """``warnings.warn(message, category)`` attributed to the innermost calling frame outside
    chunkdic (what Python 3.12's ``skip_file_prefixes`` does)."""
    frame, level = sys._getframe(1), 2  # level 2: warn_user's caller
    while frame.f_back is not None and frame.f_code.co_filename.startswith(PACKAGE_DIR):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
