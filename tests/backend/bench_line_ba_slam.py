"""Back-end cost of lines inside SLAM (not a test;
``python -m tests.backend.bench_line_ba_slam [frames] [rgbd|stereo] [seed]``).

Runs the SLAM tracker with lines on the synthetic corridor and solves every local BA twice, interleaved on
the same problem: without its lines and with them. The ratio of CPU times is the back-end overhead of the
lines, free of the run-to-run and machine-load noise of comparing two separate runs. Measured (150 frames,
31 BAs, idle 2-core machine, two runs): 236-256 vs 374-378 ms CPU per BA, 1.48-1.58x (``ba_max_lines`` 60;
40 gives 1.45x).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import vslam.mapping.local_mapping as local_mapping  # noqa: E402
from vslam.backend import ba  # noqa: E402
from vslam.data.synthetic import SyntheticConfig, SyntheticSequence  # noqa: E402
from vslam.features.lines import LineConfig  # noqa: E402
from vslam.tracking.slam import SlamConfig, SlamTracker  # noqa: E402


def main(frames: int = 150, sensor: str = "rgbd", seed: int = 0) -> None:
    solve = ba.local_bundle_adjustment
    cpu: dict[str, list[float]] = {"points": [], "lines": []}

    def both(problem, camera, cfg):
        if problem.lines is None:
            return solve(problem, camera, cfg)
        t = time.process_time()
        solve(dataclasses.replace(problem, lines=None), camera, cfg)
        cpu["points"].append(time.process_time() - t)
        t = time.process_time()
        res = solve(problem, camera, cfg)
        cpu["lines"].append(time.process_time() - t)
        return res

    local_mapping.local_bundle_adjustment = both
    seq = SyntheticSequence(SyntheticConfig(scene="corridor", n_frames=300, n_movers=0, seed=seed), sensor=sensor)
    st = SlamTracker(seq.calibration, sensor, SlamConfig(lines=LineConfig(enabled=True)))
    for i in range(frames):
        st.track(seq.frame(i))
    p, q = 1e3 * np.array(cpu["points"]), 1e3 * np.array(cpu["lines"])
    print(f"{len(p)} local BAs: CPU ms per BA without lines {p.mean():.1f}, with lines {q.mean():.1f}, "
          f"ratio {q.sum() / p.sum():.2f}")


if __name__ == "__main__":
    a = sys.argv[1:]
    main(int(a[0]) if a else 150, a[1] if len(a) > 1 else "rgbd", int(a[2]) if len(a) > 2 else 0)
