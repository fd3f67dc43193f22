"""Where the real benchmark subsets live: $VSLAM_DATA, else ../shared/data beside the checkout."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def data_root() -> Path:
    env = os.environ.get("VSLAM_DATA")
    if env:
        return Path(env).expanduser().resolve()
    for cand in (REPO_ROOT.parent / "shared" / "data", Path.cwd().parent / "shared" / "data"):
        if cand.is_dir():
            return cand
    return REPO_ROOT.parent / "shared" / "data"
