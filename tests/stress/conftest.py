"""Shared pieces of the numerical stress suite (issue 7).

The suite reuses the reconstruction tests' problem builders (``tests/reconstruction/
_problems.py``); pytest puts a test folder on ``sys.path`` only when it collects a module
from it, so the folder is added here for runs of ``tests/stress`` alone.
"""

from __future__ import annotations

import sys
from pathlib import Path

_RECONSTRUCTION_TESTS = str(Path(__file__).parents[1] / "reconstruction")
if _RECONSTRUCTION_TESTS not in sys.path:
    sys.path.append(_RECONSTRUCTION_TESTS)
