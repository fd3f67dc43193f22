import numpy as np
import pytest

from vslam.data.trajectory import Trajectory, TrajectoryWriter, read_trajectory, write_trajectory
from vslam.errors import DatasetError
from vslam.geometry import make_T, so3_exp


def _traj(n=10):
    rng = np.random.default_rng(1)
    poses = np.stack([make_T(so3_exp(rng.normal(size=3) * 0.5), rng.normal(size=3)) for _ in range(n)])
    return Trajectory(1000.0 + 0.1 * np.arange(n), poses)


@pytest.mark.parametrize("fmt", ["tum", "kitti", "euroc"])
def test_round_trip(tmp_path, fmt):
    tr = _traj()
    p = write_trajectory(tmp_path / f"t.{fmt}", tr, fmt)
    back = read_trajectory(p)  # format guessed
    np.testing.assert_allclose(back.poses, tr.poses, atol=1e-7)
    if fmt != "kitti":
        np.testing.assert_allclose(back.timestamps, tr.timestamps, atol=1e-6)


def test_writer_flushes_each_pose(tmp_path):
    p = tmp_path / "live.txt"
    w = TrajectoryWriter(p, "tum")
    w.write(1.0, np.eye(4))
    # readable before close: a crash after this line keeps the pose
    assert len(read_trajectory(p)) == 1
    w.close()


def test_bad_trajectory_files(tmp_path):
    p = tmp_path / "x.txt"
    p.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"x.txt:2: expected 8 columns, found 7"):
        read_trajectory(p, "tum")
    p.write_text("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"x.txt:2: .*goes back in time"):
        read_trajectory(p, "tum")
    p.write_text("1.0 0 0 nan 0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"x.txt:1: column 4 is not finite"):
        read_trajectory(p, "tum")
    with pytest.raises(DatasetError, match="missing trajectory file"):
        read_trajectory(tmp_path / "nope.txt")


def test_nearest_association():
    tr = Trajectory(np.array([0.0, 1.0, 2.0]), np.tile(np.eye(4), (3, 1, 1)))
    np.testing.assert_array_equal(tr.nearest(np.array([-0.5, 0.4, 0.6, 2.01, 5.0]), 0.45), [-1, 0, 1, 2, -1])
