"""End-to-end runs: whole sequences through the pipeline (synthetic and the real subsets), scored against ground
truth. Marked ``e2e`` so a quick pass can leave them out: ``pytest -m "not e2e"``."""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config, items):
    for item in items:
        if HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.e2e)
