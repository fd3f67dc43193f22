"""Entry point of the fusion experiments: ``EXPERIMENTS[name](out_dir, seed, quick) -> metrics``.

Each writes PNG plots, ``report.md`` and ``metrics.json`` into out_dir and returns the
headline metrics (JSON-safe, with 'seed_claim' and 'ours'). ``vslam.cli.fusion`` runs them as
``vslam fusion <experiment> [--out DIR] [--seed N] [--quick]``.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable


Experiment = Callable[..., dict[str, Any]]


def _lazy(module: str, name: str) -> Experiment:
    """The experiment ``module.name``, imported when first called: the experiment modules pull in scipy.stats and
    matplotlib (~0.6 s), which every other ``vslam`` command would otherwise pay at start (the CLI registers
    ``fusion`` with the rest)."""

    def run(*args: Any, **kwargs: Any) -> dict[str, Any]:
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    run.__name__ = run.__qualname__ = name
    return run


EXPERIMENTS: dict[str, Experiment] = {
    "ins_gnss": _lazy("vslam.fusion.exp_nav", "run_ins_gnss"),
    "validity": _lazy("vslam.fusion.exp_nav", "run_validity"),
    # the same mode choice, VIO channel = a real vslam trajectory
    "validity_vslam": _lazy("vslam.fusion.exp_vslam", "run_validity_vslam"),
    "identification": _lazy("vslam.fusion.exp_group", "run_identification"),
    "multi_vehicle": _lazy("vslam.fusion.exp_group", "run_multi_vehicle"),
}
