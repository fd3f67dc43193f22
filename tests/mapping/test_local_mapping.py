"""LocalMapper's batched point creation and fusion give the map that the plain one-pair-at-a-time code gives."""

import copy

import numpy as np
import pytest

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.geometry.se3 import make_T, so3_exp
from vslam.geometry.triangulation import triangulate_points
from vslam.mapping.local_mapping import GatheredPoints, LocalMapper, MappingConfig
from vslam.mapping.map import Map
from vslam.geometry.camera import project

CAM = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def _scene(seed: int, sensor: str, n_pts: int = 400, n_kf: int = 4) -> tuple[Map, np.ndarray]:
    """Keyframes moving sideways past random points: each sees the points in its image (noisy pixels, a few
    descriptor bits flipped) plus clutter keypoints; RGB-D keyframes get depths (some
    off by up to 30 %, some missing)."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-4, 4, n_pts), rng.uniform(-3, 3, n_pts), rng.uniform(4, 12, n_pts)])
    base = rng.integers(0, 256, (n_pts, 32), dtype=np.uint8)
    m = Map()
    for k in range(n_kf):
        T = make_T(so3_exp(rng.normal(0, 0.02, 3)), np.array([0.25 * k, 0.02 * k, 0.05 * k]))
        uv, z, vis = project(T, X, CAM)
        idx = np.flatnonzero(vis)
        n_clutter = 60
        kuv = np.vstack([uv[idx] + rng.normal(0, 0.4, (len(idx), 2)), rng.uniform([0, 0], [639, 479], (n_clutter, 2))])
        desc = np.vstack([base[idx], rng.integers(0, 256, (n_clutter, 32), dtype=np.uint8)])
        flips = rng.integers(0, 256, desc.shape, dtype=np.uint8) & (rng.random(desc.shape) < 0.03).astype(np.uint8)
        desc ^= flips
        octave = rng.integers(0, 3, len(kuv))
        depth = np.full(len(kuv), np.nan)
        if sensor != "mono":
            depth[: len(idx)] = z[idx] * np.where(rng.random(len(idx)) < 0.3, rng.uniform(0.7, 1.3, len(idx)), 1.0)
            depth[rng.random(len(kuv)) < 0.1] = np.nan
        feats = Features(kuv, kuv.copy(), desc, octave, np.ones(len(kuv)))
        m.add_keyframe(k, float(k), T, feats, depth, np.full(len(kuv), np.nan))
    return m, X


def _mapper(m: Map, sensor: str) -> LocalMapper:
    return LocalMapper(m, CAM, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.1), sensor,
                       MappingConfig(tri_parallax_deg=0.5, tri_max_reproj_px=3.0), BackendConfig())


def _state(m: Map):
    """Everything the map holds, as comparable values."""
    kfs = [(k, kf.point_ids.tobytes()) for k, kf in m.keyframes.items()]
    pts = [(p.id, p.xyz.tobytes(), p.descriptor.tobytes(), tuple(p.observations.items()), p.n_visible, p.n_found,
            p.first_kf) for p in m.points.values()]
    return kfs, pts, m.revision, m._next_pt


def _triangulate_plain(mapper: LocalMapper, kf, neighbors) -> list[int]:
    """LocalMapper.triangulate one pair at a time (add_point, then add_observation)."""
    new = []
    for nb_id in neighbors:
        nb = mapper.map.keyframes[nb_id]
        a, b = np.flatnonzero(kf.point_ids < 0), np.flatnonzero(nb.point_ids < 0)
        if len(a) < 8 or len(b) < 8:
            continue
        mt = mapper._tri_matches(kf, nb, a, b)
        if len(mt) == 0:
            continue
        ia, ib = a[mt[:, 0]], b[mt[:, 1]]
        X, ok = triangulate_points(kf.T_world_cam, nb.T_world_cam, kf.features.uv[ia], nb.features.uv[ib], CAM.K,
                                   mapper.cfg.tri_parallax_deg, mapper.cfg.tri_max_reproj_px)
        for j in np.flatnonzero(ok):
            mp = mapper.map.add_point(X[j], kf.id, int(ia[j]))
            mapper.map.add_observation(mp.id, nb_id, int(ib[j]))
            new.append(mp.id)
    return new


def _fuse_into_plain(self: LocalMapper, target, pids, gathered=None) -> int:
    """LocalMapper._fuse_into with numpy membership tests and one pair at a time (the depth test on scalars)."""
    pids = np.asarray(pids, np.int64)
    pids = pids[~np.isin(pids, target.point_ids)]
    pids = pids[np.array([int(p) in self.map.points for p in pids], bool)]
    if len(pids) == 0 or len(target.features) == 0:
        return 0
    g = gathered if gathered is not None else GatheredPoints(self.map, pids)
    rows = g.rows(pids)
    uv, z, vis = project(target.T_world_cam, g.xyz[rows], self.cam)
    idx = np.flatnonzero(vis)
    if len(idx) == 0:
        return 0
    from vslam.mapping.local_mapping import match_by_projection
    pairs = match_by_projection(uv[idx], g.desc[rows[idx]], target.features.uv, target.features.desc,
                                self.cfg.fuse_radius_px, self.cfg.max_hamming, 1.0)
    n = 0
    for pi, kp in pairs:
        pid = int(pids[idx[pi]])
        zk = target.depth[kp]
        if np.isfinite(zk) and abs(zk - z[idx[pi]]) > 0.1 * zk:
            continue
        if pid not in self.map.points or target.id in self.map.points[pid].observations:
            continue
        old = int(target.point_ids[kp])
        if old < 0:
            self.map.add_observation(pid, target.id, int(kp))
        else:
            keep, drop = (old, pid) if len(self.map.points[old].observations) >= len(self.map.points[pid].observations) else (pid, old)
            self.map.merge_points(keep, drop)
        n += 1
    return n


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_triangulate_equals_one_pair_at_a_time(seed):
    m, _ = _scene(seed, "mono")
    ref = copy.deepcopy(m)
    kf = m.keyframes[3]
    new = _mapper(m, "mono").triangulate(kf, [2, 1, 0])
    want = _triangulate_plain(_mapper(ref, "mono"), ref.keyframes[3], [2, 1, 0])
    assert len(new) > 50
    assert new == want
    assert _state(m) == _state(ref)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sensor", ["rgbd", "mono"])
def test_fuse_equals_the_plain_pair_loop(seed, sensor, monkeypatch):
    """Each keyframe back-projects (RGB-D) or triangulates (mono) its own copies of the points, so fusion merges
    duplicates, attaches free keypoints and skips depth clashes; the map after it is the plain loop's."""
    m, _ = _scene(seed, sensor)
    mapper = _mapper(m, sensor)
    for k in range(4):
        kf = m.keyframes[k]
        if sensor == "mono":
            mapper.triangulate(kf, [j for j in range(k)][-2:])
        else:
            mapper.create_depth_points(kf)
    ref = copy.deepcopy(m)
    ref_mapper = _mapper(ref, sensor)
    monkeypatch.setattr(LocalMapper, "_fuse_into", _fuse_into_plain)
    ref_mapper.fuse(ref.keyframes[3], [2, 1, 0])
    monkeypatch.undo()
    n_before = len(m.points)
    mapper.fuse(m.keyframes[3], [2, 1, 0])
    assert len(m.points) < n_before  # duplicates were merged
    assert _state(m) == _state(ref)


def test_fuse_into_a_list_of_ids_skips_removed_and_seen_ones():
    """Loop fusion's call: a plain id list with ids merged away, already seen by the target, or repeated."""
    m, _ = _scene(3, "rgbd")
    mapper = _mapper(m, "rgbd")
    for k in range(4):
        mapper.create_depth_points(m.keyframes[k])
    ids = list(m.keyframes[0].point_ids[m.keyframes[0].point_ids >= 0][:150]) + [10**6, -1]
    ids += list(m.keyframes[1].point_ids[:20])  # -1s and ids kf1 already sees
    for p in ids[:10]:
        m.remove_point(int(p))
    ref = copy.deepcopy(m)
    n = mapper._fuse_into(m.keyframes[1], ids)
    assert n == _fuse_into_plain(_mapper(ref, "rgbd"), ref.keyframes[1], ids)
    assert _state(m) == _state(ref)


@pytest.mark.parametrize("full", [0, 12])
def test_full_ba_keyframes_adjusts_every_early_keyframe(full):
    """Monocular, map of at most full_ba_keyframes keyframes: the new keyframe's BA frees every keyframe but the
    first (held fixed); beyond it (or off) the covisibility window of ba_window keyframes."""
    m, X = _scene(3, "mono", n_kf=12)
    # every true point seen by the first keyframe joins the map, observed wherever it is in view (the scene's
    # keypoints list the visible points first, in order)
    uv0, _, vis0 = project(m.keyframes[0].T_world_cam, X, CAM)
    ids = {}
    for j in np.flatnonzero(vis0):
        ids[j] = m.add_point(X[j], 0, int(np.searchsorted(np.flatnonzero(vis0), j))).id
    for k in range(1, 12):
        _, _, vis = project(m.keyframes[k].T_world_cam, X, CAM)
        for pos, j in enumerate(np.flatnonzero(vis)):
            if j in ids:
                m.add_observation(ids[j], k, pos)
    mapper = LocalMapper(m, CAM, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.0), "mono",
                         MappingConfig(ba_window=4, full_ba_keyframes=full), BackendConfig())
    problem = mapper._ba_job(11)[0]
    free = set(problem.poses) - problem.fixed
    if full:
        assert free == set(range(1, 12)) and problem.fixed == {0}
    else:
        assert 11 in free and len(free) <= 4
