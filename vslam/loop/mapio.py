"""Map save / load: keyframes, map points and place descriptors in one versioned ``.npz`` file.

Layout (``FORMAT_VERSION`` 1): a JSON ``header`` (format name, version, counts, descriptor kind and dim,
next ids, the sensor that made it, the map ids and which one was current) plus flat numpy arrays -- per keyframe its pose and the offsets of its keypoints in the
concatenated per-keypoint arrays (raw, uv, desc, octave, response, depth, ur, point_ids), per point its
position, representative descriptor, first keyframe and visibility counters, and one place-descriptor row
per keyframe; ``kf_map`` says which map (``vslam.tracking.atlas``: a run that lost tracking has several; a
file without it holds one). Observations are not stored: they are exactly the keyframes' ``point_ids`` and are rebuilt
from them, so the file cannot hold an inconsistent map. numpy only (``allow_pickle=False``): a map file
never executes code when loaded.
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vslam.errors import VslamError
from vslam.features.base import Features
from vslam.loop.database import KeyframeDatabase
from vslam.mapping.map import KeyFrame, Map, MapPoint, PoseLink

FORMAT = "vslam-map"
FORMAT_VERSION = 1


class MapFileError(VslamError):
    """A map file that is missing, of another format or version, or inconsistent."""


@dataclass
class LoadedMap:
    map: Map  # the map that was current when saved
    database: KeyframeDatabase  # its keyframes' place descriptors
    header: dict
    current: int = 0
    others: dict[int, tuple[Map, KeyframeDatabase]] = dataclasses.field(default_factory=dict)  # the other maps


def save_map(path: str | Path, m: Map, database: KeyframeDatabase, descriptor_kind: str = "bow",
             sensor: dict | None = None, others: dict[int, Map] | None = None, current: int = 0) -> Path:
    """Write ``m`` (map id ``current``), the ``others`` maps of the run, and the place descriptors of all their
    keyframes (every keyframe must be in ``database``).

    ``sensor``: what made the map (``sensor_header``), so that a run with another camera, sensor or keypoint
    type refuses it instead of tracking nothing against it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    maps = {current: m, **(others or {})}
    kfs = [kf for mm in maps.values() for kf in mm.keyframes.values()]
    kf_map = np.array([mid for mid, mm in maps.items() for _ in mm.keyframes], np.int64)
    missing = [k.id for k in kfs if k.id not in database]
    if missing:
        raise MapFileError(f"{path}: keyframes {missing[:5]} have no place descriptor")
    n_kp = np.array([len(k.features) for k in kfs], np.int64)
    off = np.r_[0, np.cumsum(n_kp)]

    def cat(get, dtype=None) -> np.ndarray:
        parts = [np.asarray(get(k)) for k in kfs]
        out = np.concatenate(parts) if parts else np.zeros(0)
        return out.astype(dtype) if dtype is not None else out

    pts = [mp for mm in maps.values() for mp in mm.points.values()]
    header = {"format": FORMAT, "version": FORMAT_VERSION, "keyframes": len(kfs), "points": len(pts),
              "descriptor": descriptor_kind, "descriptor_dim": database.dim,
              "next_kf": max(mm._next_kf for mm in maps.values()), "next_pt": max(mm._next_pt for mm in maps.values()),
              "maps": sorted(maps), "current": current, **({"sensor": sensor} if sensor else {})}
    arrays = {
        "header": np.frombuffer(json.dumps(header).encode(), np.uint8),
        "kf_id": np.array([k.id for k in kfs], np.int64),
        "kf_map": kf_map,
        "kf_frame_index": np.array([k.frame_index for k in kfs], np.int64),
        "kf_timestamp": np.array([k.timestamp for k in kfs], np.float64),
        "kf_T": np.array([k.T_world_cam for k in kfs], np.float64).reshape(-1, 4, 4),
        "kf_scale_factor": np.array([k.features.scale_factor for k in kfs], np.float64),
        "kf_offset": off,
        "kf_place": np.array([database.vector(k.id) for k in kfs], np.float32).reshape(-1, database.dim),
        "kp_raw": cat(lambda k: k.features.raw, np.float64).reshape(-1, 2),
        "kp_uv": cat(lambda k: k.features.uv, np.float64).reshape(-1, 2),
        "kp_desc": cat(lambda k: k.features.desc),
        "kp_octave": cat(lambda k: k.features.octave, np.int64),
        "kp_response": cat(lambda k: k.features.response, np.float64),
        "kp_depth": cat(lambda k: k.depth, np.float64),
        "kp_ur": cat(lambda k: k.ur, np.float64),
        "kp_point": cat(lambda k: k.point_ids, np.int64),
        "pt_id": np.array([p.id for p in pts], np.int64),
        "pt_xyz": np.array([p.xyz for p in pts], np.float64).reshape(-1, 3),
        "pt_desc": np.array([p.descriptor for p in pts]),
        "pt_first_kf": np.array([p.first_kf for p in pts], np.int64),
        "pt_visible": np.array([[p.n_visible, p.n_found] for p in pts], np.int64).reshape(-1, 2),
        "link_kf": np.array([(ln.a, ln.b) for mm in maps.values() for ln in mm.links], np.int64).reshape(-1, 2),
        "link_T": np.array([ln.T_a_b for mm in maps.values() for ln in mm.links], np.float64).reshape(-1, 4, 4),
        "link_cov": np.array([ln.cov for mm in maps.values() for ln in mm.links], np.float64).reshape(-1, 6, 6),
    }
    from vslam.outputs import atomic_open

    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


def sensor_header(sensor: str, cam, extractor: str) -> dict:
    """The map header's record of what made the map: sensor kind, keypoint extractor, intrinsics."""
    return {"kind": sensor, "extractor": extractor, "width": int(cam.width), "height": int(cam.height),
            "fx": float(cam.fx), "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy)}


def check_sensor(path: str | Path, header: dict, want: dict, rel_tol: float = 0.005) -> None:
    """MapFileError when the map was made by another camera (size, intrinsics beyond ``rel_tol``), by another
    keypoint extractor (its descriptors cannot match), or monocularly (no metric scale) for a run with depth.
    A map file written before the header held the sensor is accepted with a warning."""
    have = header.get("sensor")
    if not isinstance(have, dict):
        import logging

        logging.getLogger(__name__).warning("%s: the map file does not say which camera made it; it is assumed "
                                            "to be this run's", path)
        return
    where = f"{path}: map made"
    if have.get("extractor") != want["extractor"]:
        raise MapFileError(f"{where} with {have.get('extractor')!r} keypoints, this run uses {want['extractor']!r} "
                           "(slam.features.extractor)")
    if have.get("kind") == "mono" and want["kind"] != "mono":
        raise MapFileError(f"{where} monocularly has no metric scale; this run is {want['kind']} (a metric map "
                           "serves a monocular run, not the other way round)")
    for k in ("width", "height", "fx", "fy", "cx", "cy"):
        a, b = float(have.get(k, float("nan"))), float(want[k])
        if not abs(a - b) <= rel_tol * max(abs(b), 1.0):
            raise MapFileError(f"{where} by another camera: {k} {a:g}, this run's camera {b:g}")


def load_map(path: str | Path) -> LoadedMap:
    """Read a file written by ``save_map`` -> the map (observations rebuilt) and its keyframe database."""
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"{path}: map file not found")
    try:
        with np.load(path, allow_pickle=False) as f:
            z = {k: f[k] for k in f.files}  # NpzFile decompresses on every access: read each array once
        header = json.loads(bytes(z["header"]).decode())
        if not isinstance(header, dict):
            raise ValueError("header is not a JSON object")
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise MapFileError(f"{path}: not a vslam map file ({e})") from None
    if header.get("format") != FORMAT or header.get("version") != FORMAT_VERSION:
        raise MapFileError(f"{path}: format {header.get('format')!r} version {header.get('version')!r}, "
                           f"expected {FORMAT!r} version {FORMAT_VERSION}")
    try:
        return _rebuild(path, z, header)
    except (KeyError, IndexError, ValueError, TypeError, AttributeError) as e:  # arrays missing or inconsistent
        raise MapFileError(f"{path}: corrupt map file ({e!r})") from None


def _rebuild(path: Path, z: dict, header: dict) -> LoadedMap:
    m = Map()
    off = z["kf_offset"]
    for i, kid in enumerate(z["kf_id"].tolist()):
        s = slice(int(off[i]), int(off[i + 1]))
        feats = Features(z["kp_raw"][s], z["kp_uv"][s], z["kp_desc"][s], z["kp_octave"][s], z["kp_response"][s],
                         float(z["kf_scale_factor"][i]))
        m.keyframes[kid] = KeyFrame(kid, int(z["kf_frame_index"][i]), float(z["kf_timestamp"][i]), z["kf_T"][i].copy(),
                                    feats, z["kp_depth"][s].copy(), z["kp_ur"][s].copy(), z["kp_point"][s].copy())
    for j, pid in enumerate(z["pt_id"].tolist()):
        nv, nf = z["pt_visible"][j].tolist()
        m.points[pid] = MapPoint(pid, z["pt_xyz"][j].copy(), z["pt_desc"][j].copy(), int(z["pt_first_kf"][j]), {}, nv, nf)
    for kf in m.keyframes.values():
        for kp in np.flatnonzero(kf.point_ids >= 0).tolist():
            pid = int(kf.point_ids[kp])
            if pid not in m.points:
                raise MapFileError(f"{path}: keyframe {kf.id} observes unknown point {pid}")
            m.points[pid].observations[kf.id] = kp
    # never reuse an id, even if the header's counters are behind the stored ids
    m._next_kf = max(int(header["next_kf"]), max(m.keyframes, default=-1) + 1)
    m._next_pt = max(int(header["next_pt"]), max(m.points, default=-1) + 1)
    kf_map = z["kf_map"].tolist() if "kf_map" in z else [0] * len(z["kf_id"])
    of = dict(zip(z["kf_id"].tolist(), kf_map))
    current = int(header.get("current", 0))
    maps: dict[int, tuple[Map, KeyframeDatabase]] = {}
    for mid in sorted(set(kf_map) | {current}):
        part = Map()
        part._next_kf, part._next_pt = m._next_kf, m._next_pt
        maps[mid] = (part, KeyframeDatabase(int(header["descriptor_dim"])))
    for kid, v in zip(z["kf_id"].tolist(), z["kf_place"]):
        part, db = maps[of[kid]]
        part.keyframes[kid] = m.keyframes[kid]
        db.add(kid, v)
    for pid, mp in m.points.items():
        if not mp.observations:
            raise MapFileError(f"{path}: point {pid} is observed by no keyframe")
        home = {of[k] for k in mp.observations}
        if len(home) != 1:
            raise MapFileError(f"{path}: point {pid} is observed in maps {sorted(home)}")
        maps[home.pop()][0].points[pid] = mp
    links = z.get("link_kf", np.zeros((0, 2), np.int64)).tolist()  # files written before links have none
    if links and not len(links) == len(z["link_T"]) == len(z["link_cov"]):
        raise MapFileError(f"{path}: {len(links)} pose links but {len(z['link_T'])} poses and "
                           f"{len(z['link_cov'])} covariances")
    for (a, b), T, cov in zip(links, z.get("link_T", ()), z.get("link_cov", ())):
        if of.get(a) != of.get(b) or a not in of:
            raise MapFileError(f"{path}: pose link {a}->{b} joins keyframes of different or no maps")
        maps[of[a]][0].links.append(PoseLink(a, b, T.copy(), cov.copy()))
    cur_map, cur_db = maps.pop(current)
    return LoadedMap(cur_map, cur_db, header, current, maps)
