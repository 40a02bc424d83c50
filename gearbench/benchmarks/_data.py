"""Where the shared data sets are: ``../shared`` beside the repository checkout.

Never an absolute path of one machine: CI runs a clean clone with the shared folder
beside it, and a developer's checkout may live anywhere.
"""
from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SHARED_DIR = REPO_ROOT.parent / "shared"
DEV_DIR = SHARED_DIR / "datasets" / "dev"            # independent simulator, known truth (truth.json)
