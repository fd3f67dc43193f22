"""Files a run writes (``vslam.outputs``)."""

import numpy as np

from vslam.outputs import write_map_ply


def test_map_ply_reads_back_exactly(tmp_path):
    """map.ply is written without open3d (its import is ~160 MB resident at the end of a run); open3d still reads
    it, point for point."""
    import open3d as o3d

    xyz = np.random.default_rng(0).normal(size=(100, 3)) * 50
    path = write_map_ply(tmp_path / "map.ply", xyz)
    np.testing.assert_array_equal(np.asarray(o3d.io.read_point_cloud(str(path)).points), xyz)
    assert b"element vertex 0\n" in write_map_ply(tmp_path / "empty.ply", np.zeros((0, 3))).read_bytes()
