"""Puts the checkout's root on ``sys.path``, so that a script run as ``python scripts/NAME.py`` imports the
experiment code of the top-level ``experiments/`` folder, which stays out of the installed package."""

import sys
from pathlib import Path

ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
