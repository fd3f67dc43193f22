"""The networks, their trainers and the network-speed row import with torch, numpy, cv2 (and scipy) alone: the
GPU machine has no gtsam, pycolmap, open3d, evo or ray."""

from __future__ import annotations

import subprocess
import sys

BLOCK = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('gtsam', 'pycolmap', 'open3d', 'evo', 'ray'):
            raise ImportError('not on the GPU machine: ' + name)
sys.meta_path.insert(0, Block())
"""


def test_networks_import_without_the_slam_back_end():
    mods = ["vslam.nn.device", "vslam.train.detector", "vslam.dynamic.detector", "vslam.train.keypoints",
            "vslam.features.convpoint", "vslam.loop.vladnet", "vslam.train.place", "vslam.profiling", "vslam.bench",
            "vslam.cli"]
    code = BLOCK + "".join(f"import {m}\n" for m in mods) + "from vslam.profiling import network_speed\n"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
