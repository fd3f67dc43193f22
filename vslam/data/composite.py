"""``vslam make-dynamic``: a dynamic RGB-D benchmark on real backgrounds.

COCO person cutouts (COCO128 instance polygons) become vertical 3-D billboards that walk on smooth paths
through a real TUM RGB-D sequence; each frame is rendered with the ground-truth camera pose: the cutout is
warped by the plane's homography, its per-pixel depth is the ray / plane intersection, and it is drawn only
where it is nearer than the recorded depth (occlusion; invalid depth counts as far). Outputs the TUM layout
(rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt) plus masks/ (PNG, 255 on a visible person) and boxes.txt,
so the same SLAM run on the clean and the composited frames gives the ATE ratio dynamic-object filtering is judged by.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from vslam.data.types import Frame, PinholeCamera
from vslam.errors import DatasetError
from vslam.progress import Progress

log = logging.getLogger(__name__)

# Changes whenever the same seed renders other frames, so cached composites (``vslam bench``) are made again:
# 2 = TUM walkers upright along gravity, feet on the floor (1: along the first camera's -y, leaning ~26 degrees).
GENERATOR_VERSION = 2


@dataclass(frozen=True)
class Billboard:
    """A vertical rectangle in the world: centre (3,) at time 0, up (3,) unit, height in metres; the cutout
    (h,w,4) BGRA fixes the width by its aspect. It walks ``centre + amp * sin(omega t + phase) * direction``."""

    cutout: np.ndarray
    centre: np.ndarray
    up: np.ndarray
    height: float
    direction: np.ndarray
    amp: float
    omega: float
    phase: float

    def corners_world(self, t: float, cam_centre: np.ndarray) -> np.ndarray:
        """(4,3) world corners top-left, top-right, bottom-right, bottom-left; the plane turns to face the camera
        about the up axis (a billboard)."""
        c = self.centre + self.amp * np.sin(self.omega * t + self.phase) * self.direction
        view = cam_centre - c
        view = view - self.up * (view @ self.up)
        n = view / max(np.linalg.norm(view), 1e-9)
        right = np.cross(self.up, n)
        h, w = self.cutout.shape[:2]
        half_w, half_h = 0.5 * self.height * w / h, 0.5 * self.height
        return np.array([c - right * half_w + self.up * half_h, c + right * half_w + self.up * half_h,
                         c + right * half_w - self.up * half_h, c - right * half_w - self.up * half_h])


def render_billboard(corners_cam: np.ndarray, K: np.ndarray, cutout: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Corners (4,3) in the camera frame -> (colour (H,W,3) uint8, alpha mask (H,W) bool, depth (H,W) float32
    metres along z, inf off the billboard), or None when any corner is behind the camera."""
    if np.any(corners_cam[:, 2] <= 0.05):
        return None
    H, W = shape
    uv = (corners_cam @ K.T)[:, :2] / corners_cam[:, 2:3]
    h, w = cutout.shape[:2]
    src = np.float32([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])  # outer pixel edges
    Hm = cv2.getPerspectiveTransform(src, uv.astype(np.float32))
    # colour with replicated borders, alpha with a zero border: edge pixels keep the cutout's colour
    colour = cv2.warpPerspective(np.ascontiguousarray(cutout[..., :3]), Hm, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    alpha = cv2.warpPerspective(np.ascontiguousarray(cutout[..., 3]), Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=0) >= 128
    # depth of the plane along each pixel's ray: z = (n . p0) / (n . K^-1 [u v 1])
    n = np.cross(corners_cam[1] - corners_cam[0], corners_cam[3] - corners_cam[0])
    rays = np.linalg.inv(K) @ np.vstack([*np.meshgrid(np.arange(W) + 0.0, np.arange(H) + 0.0), np.ones((H, W))]).reshape(3, -1)
    denom = n @ rays
    z = np.where(np.abs(denom) > 1e-12, (n @ corners_cam[0]) / np.where(denom == 0, 1, denom), np.inf).reshape(H, W)
    depth = np.where(alpha & (z > 0), z, np.inf).astype(np.float32)
    return colour, alpha & np.isfinite(depth), depth


def composite(image: np.ndarray, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, t: float,
              boards: list[Billboard]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame: image (H,W,3) BGR, depth (H,W) metres (0 invalid), pose, time -> composited image, depth,
    mask (H,W) bool of visible billboard pixels, boxes (K,4) of each visible billboard's mask."""
    img, dep = image.copy(), depth.astype(np.float32).copy()
    scene = np.where(dep > 0, dep, np.inf)
    mask = np.zeros(depth.shape, bool)
    T_cam_world = np.linalg.inv(T_world_cam)
    boxes = []
    for b in boards:
        cw = b.corners_world(t, T_world_cam[:3, 3])
        r = render_billboard(cw @ T_cam_world[:3, :3].T + T_cam_world[:3, 3], K, b.cutout, depth.shape)
        if r is None:
            continue
        col, alpha, z = r
        vis = alpha & (z < scene)  # nearer than the recorded surface (or than a billboard already drawn)
        if not vis.any():
            continue
        img[vis], dep[vis], scene[vis] = col[vis], z[vis], z[vis]
        mask |= vis
        ys, xs = np.nonzero(vis)
        boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
    return img, dep, mask, np.array(boxes, np.float64).reshape(-1, 4)


def person_instances(coco_root: str | Path, min_height_px: int = 120, min_aspect: float = 1.8, whole: bool = True,
                     person_id: str = "1", exclude: frozenset[str] = frozenset()) -> list[tuple[str, np.ndarray]]:
    """(image stem, BGRA crop) of COCO128 person instances, alpha from their polygons, largest first.
    ``segments/`` rows are "category x1 y1 x2 y2 ..." normalised, with the original COCO category ids (1 =
    person, unlike ``labels/``). ``whole``: only instances that do not touch the image border; ``min_aspect``:
    height / width at least this (upright figures); images whose stem is in ``exclude`` are skipped."""
    root = Path(coco_root)
    found = []
    for seg in sorted((root / "segments" / "train2017").glob("*.txt")):
        if seg.stem in exclude:
            continue
        img = None
        for line in seg.read_text().splitlines():
            v = line.split()
            if not v or v[0] != person_id or len(v) < 7:
                continue
            if img is None:
                img = cv2.imread(str(root / "images" / "train2017" / (seg.stem + ".jpg")), cv2.IMREAD_COLOR)
                if img is None:
                    break
            h, w = img.shape[:2]
            poly = (np.array(v[1:], np.float64).reshape(-1, 2) * [w, h]).astype(np.int32)
            x0, y0 = np.maximum(poly.min(0), 0)
            x1, y1 = np.minimum(poly.max(0) + 1, [w, h])
            if y1 - y0 < min_height_px or y1 - y0 < min_aspect * (x1 - x0):
                continue
            if whole and (x0 <= 0 or y0 <= 0 or x1 >= w or y1 >= h):
                continue
            a = np.zeros((h, w), np.uint8)
            cv2.fillPoly(a, [poly], 255)
            found.append((int(a.sum()), seg.stem, np.dstack([img, a])[y0:y1, x0:x1].copy()))
    found.sort(key=lambda x: -x[0])
    return [(stem, c) for _, stem, c in found]


def person_cutouts(coco_root: str | Path, limit: int = 20) -> list[np.ndarray]:
    """The benchmark's walkers: the ``limit`` largest whole, upright COCO128 person instances (close-up
    portraits would become giant heads)."""
    found = person_instances(coco_root)
    if not found:
        raise DatasetError(Path(coco_root) / "segments" / "train2017", "no whole person instance of at least 120 px")
    return [c for _, c in found[:limit]]


def benchmark_stems(coco_root: str | Path, limit: int = 20) -> frozenset[str]:
    """COCO128 images whose people walk through the dynamic benchmark: the detector never trains on them."""
    return frozenset(stem for stem, _ in person_instances(coco_root)[:limit])


@dataclass(frozen=True)
class MakeDynamicConfig:
    n_people: int = 3
    seed: int = 0
    max_frames: int | None = None
    distance: tuple[float, float] = (1.5, 3.0)  # metres ahead of the first camera
    height: tuple[float, float] = (1.2, 1.7)  # billboard height, metres
    speed: tuple[float, float] = (0.3, 0.8)  # m/s, peak walking speed
    amp: tuple[float, float] = (0.4, 0.8)  # metres, half the walk
    camera_height: float = 1.65  # KITTI: metres from the camera down to the road (walkers stand on it)
    max_range: float = 25.0  # KITTI: walkers further than this are not drawn (no depth to hide them behind houses)

    @classmethod
    def for_kitti(cls, n_people: int = 6, seed: int = 0, max_frames: int | None = None) -> "MakeDynamicConfig":
        """Walkers for a driving sequence: people-sized, crossing the road 6-14 m ahead of where the car is when
        each one appears, at walking speed."""
        return cls(n_people=n_people, seed=seed, max_frames=max_frames, distance=(6.0, 14.0), height=(1.6, 1.85),
                   speed=(1.0, 1.5), amp=(1.0, 2.0))


def world_up(poses: np.ndarray) -> np.ndarray:
    """Gravity's up in the world frame of a hand-held or driven camera's poses (N,4,4) T_world_cam: the normal
    of the plane that the cameras' x axes (image right) span, since such cameras keep their roll small (a
    TUM mocap frame's axes are not documented, and a camera looking down at the scene has its -y off
    vertical by its pitch). Signed to agree with the cameras' -y.
    A camera that never turns leaves the plane undefined: then the mean -y with the mean x taken out."""
    X = poses[:, :3, 0]
    cam_up = -poses[:, :3, 1].mean(0)
    _, s, vt = np.linalg.svd(X)
    if len(X) >= 3 and s[1] > 0.1 * s[0]:
        up = vt[-1]
    else:
        x = X.mean(0) / max(np.linalg.norm(X.mean(0)), 1e-9)
        up = cam_up - x * (cam_up @ x)
    up = up / max(np.linalg.norm(up), 1e-9)
    return up if up @ cam_up >= 0 else -up


def floor_height(depth: np.ndarray, cam: PinholeCamera, T_world_cam: np.ndarray, up: np.ndarray) -> float | None:
    """Height along ``up`` of the lowest surface a depth image (metres, 0 invalid; undistorted ``cam``) sees (its
    2nd percentile: the floor where the floor is in view), or None without enough valid depth."""
    v, u = np.nonzero(depth > 0)
    if len(u) < 1000:
        return None
    X_cam = cam.backproject(np.c_[u, v], depth[v, u])
    heights = X_cam @ (T_world_cam[:3, :3].T @ up) + T_world_cam[:3, 3] @ up
    return float(np.percentile(heights, 2))


def place_people(cutouts: list[np.ndarray], T_world_cam0: np.ndarray, cfg: MakeDynamicConfig, rng: np.random.Generator,
                 up: np.ndarray | None = None, floor: float | None = None) -> list[Billboard]:
    """Billboards ahead of the first camera, upright along ``up`` (gravity: ``world_up``; None = the first
    camera's -y), walking left-right; each stands on ``floor`` (a height along ``up``) where it is known, else
    its centre is 0.2 m below the point ``distance`` ahead along the first camera's axis."""
    R, C = T_world_cam0[:3, :3], T_world_cam0[:3, 3]
    up = -R[:, 1] if up is None else up / np.linalg.norm(up)
    axis = R[:, 2]
    fwd = axis - up * (axis @ up)
    fwd = fwd / max(np.linalg.norm(fwd), 1e-9)
    right = np.cross(fwd, up)
    boards = []
    for k in range(cfg.n_people):
        d = rng.uniform(*cfg.distance)
        ahead = C + d * axis + rng.uniform(-0.5, 0.5) * d * right - 0.2 * up
        amp = rng.uniform(*cfg.amp)
        cutout, height = cutouts[int(rng.integers(len(cutouts)))], rng.uniform(*cfg.height)
        centre = ahead if floor is None else ahead + (floor + 0.5 * height - ahead @ up) * up
        boards.append(Billboard(cutout, centre, up, height, right, amp, rng.uniform(*cfg.speed) / amp,
                                rng.uniform(0, 2 * np.pi)))
    return boards


def place_walkers_on_road(cutouts: list[np.ndarray], poses: np.ndarray, cfg: MakeDynamicConfig,
                          rng: np.random.Generator) -> list[tuple[int, Billboard]]:
    """(first frame, billboard): walker k appears at frame ``k * n / n_people`` (spread along the drive), standing
    on the road (``camera_height`` below that camera) ``distance`` ahead, 1-4 m to either side, crossing."""
    out = []
    n = len(poses)
    for k in range(cfg.n_people):
        f = int(k * n / max(1, cfg.n_people))
        R, C = poses[f][:3, :3], poses[f][:3, 3]
        down, fwd, right = R[:, 1], R[:, 2], R[:, 0]
        h = rng.uniform(*cfg.height)
        centre = C + rng.uniform(*cfg.distance) * fwd + rng.choice([-1, 1]) * rng.uniform(1.0, 4.0) * right + (cfg.camera_height - h / 2) * down
        amp = rng.uniform(*cfg.amp)
        out.append((f, Billboard(cutouts[int(rng.integers(len(cutouts)))], centre, -down, h, right, amp,
                                 rng.uniform(*cfg.speed) / amp, rng.uniform(0, 2 * np.pi))))
    return out


def composited_kitti_frames(seq_dir: str | Path, coco_root: str | Path, cfg: MakeDynamicConfig) -> Iterator[tuple[Frame, np.ndarray, np.ndarray, np.ndarray]]:
    """The KITTI sequence ``seq_dir`` (grey, mono) with people crossing the road: per frame (original frame,
    composited grey image, person mask, boxes). No depth is recorded, so the scene occludes nothing: a walker is
    drawn when in front of the camera and nearer than ``max_range`` (they stand on the open road ahead)."""
    from vslam.data.kitti import KittiSequence

    seq = KittiSequence(seq_dir, sensor="mono")
    gt = seq.groundtruth()
    if gt is None:
        raise DatasetError(seq_dir, "make-dynamic needs the ground-truth poses (poses/NN.txt)")
    n = len(seq) if cfg.max_frames is None else min(len(seq), cfg.max_frames)
    walkers = place_walkers_on_road(person_cutouts(coco_root), gt.poses[:n], cfg, np.random.default_rng(cfg.seed))
    K, stamps = seq.calibration.cam0.K, seq.timestamps()
    for i in range(n):
        fr = seq.frame(i)
        grey = fr.image
        C = gt.poses[i][:3, 3]
        active = [b for _, b in walkers if np.linalg.norm(b.centre - C) < cfg.max_range]  # (nothing occludes them)
        t = float(stamps[i])
        img, _, mask, boxes = composite(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), np.zeros(grey.shape, np.float32), K,
                                        gt.poses[i], t, active)
        yield fr, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), mask, boxes


def composited_frames(seq_dir: str | Path, coco_root: str | Path, cfg: MakeDynamicConfig = MakeDynamicConfig(),
                      start: int = 0) -> Iterator[tuple[Frame, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The TUM RGB-D sequence ``seq_dir`` with walking people: per frame from the ``start``-th on (original frame,
    composited image BGR, depth metres, person mask (H,W) bool, person boxes (K,4) x1,y1,x2,y2 exclusive).
    Frames before the first ground-truth pose pass through unchanged (the walkers are placed ahead of the first
    posed camera, so they are the same whatever ``start`` is)."""
    from vslam.data.tum import TumRgbdSequence

    seq = TumRgbdSequence(seq_dir)
    cam = seq.calibration.cam0
    if cam.is_distorted:
        raise DatasetError(seq_dir, "make-dynamic renders with a pinhole model; the images must be undistorted (freiburg3)")
    rng = np.random.default_rng(cfg.seed)
    cutouts = person_cutouts(coco_root)
    posed = [T for T in (seq.frame_pose(i) for i in range(len(seq))) if T is not None]
    up = world_up(np.array(posed)) if posed else None
    boards: list[Billboard] | None = None
    t0 = 0.0
    for i, fr in enumerate(seq):
        if cfg.max_frames is not None and i >= cfg.max_frames:
            break
        img = fr.image if fr.image.ndim == 3 else cv2.cvtColor(fr.image, cv2.COLOR_GRAY2BGR)
        depth = fr.depth if fr.depth is not None else np.zeros(img.shape[:2], np.float32)
        mask, boxes = np.zeros(img.shape[:2], bool), np.zeros((0, 4))
        if fr.T_world_cam is not None:
            if boards is None:
                floor = floor_height(depth, cam, fr.T_world_cam, up) if fr.depth is not None else None
                boards, t0 = place_people(cutouts, fr.T_world_cam, cfg, rng, up, floor), fr.timestamp
            if i >= start:
                img, depth, mask, boxes = composite(img, depth, cam.K, fr.T_world_cam, fr.timestamp - t0, boards)
        if i >= start:
            yield fr, img, depth, mask, boxes


def make_dynamic(seq_dir: str | Path, out_dir: str | Path, coco_root: str | Path, cfg: MakeDynamicConfig = MakeDynamicConfig(),
                 progress: Progress | None = None) -> Path:
    """Composite walking people into the TUM RGB-D or KITTI sequence ``seq_dir``; write its layout + masks to
    ``out_dir``. Returns the folder to give ``dataset.path`` (for KITTI ``out_dir/sequences/NN``).
    ``progress(done, total)`` after each frame written."""
    from vslam.data.kitti import is_kitti_layout

    if is_kitti_layout(Path(seq_dir)):
        return _make_dynamic_kitti(Path(seq_dir), Path(out_dir), coco_root, cfg, progress)
    return _make_dynamic_tum(seq_dir, out_dir, coco_root, cfg, progress)


def _box_lines(stamp: str, boxes: np.ndarray) -> list[str]:
    return [f"{stamp} {k} {b[0]:.0f} {b[1]:.0f} {b[2] - 1:.0f} {b[3] - 1:.0f}\n" for k, b in enumerate(boxes)]


BOXES_HEADER = "# timestamp object_id x1 y1 x2 y2 (inclusive pixels)\n"


def _make_dynamic_kitti(seq_dir: Path, out_dir: Path, coco_root: str | Path, cfg: MakeDynamicConfig,
                        progress: Progress | None = None) -> Path:
    import shutil

    from vslam.data.kitti import resolve_sequence_dir

    src, poses = resolve_sequence_dir(seq_dir, None)
    out = out_dir / "sequences" / src.name
    for sub in ("image_0", "mask_0"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    box_lines, n = [], 0
    times = (src / "times.txt").read_text().splitlines(keepends=True)
    total = len(times) if cfg.max_frames is None else min(len(times), cfg.max_frames)
    for fr, img, mask, boxes in composited_kitti_frames(src, coco_root, cfg):
        cv2.imwrite(str(out / "image_0" / f"{fr.index:06d}.png"), img)
        cv2.imwrite(str(out / "mask_0" / f"{fr.index:06d}.png"), mask.astype(np.uint8) * 255)
        box_lines += _box_lines(f"{fr.timestamp:.6f}", boxes)
        n += 1
        if progress is not None:
            progress(n, total)
    (out / "times.txt").write_text("".join(times[:n]))
    shutil.copy(src / "calib.txt", out / "calib.txt")
    (out_dir / "poses").mkdir(parents=True, exist_ok=True)
    assert poses is not None  # composited_kitti_frames refused a sequence without
    rows = poses.read_text().splitlines(keepends=True)
    (out_dir / "poses" / f"{src.name}.txt").write_text("".join(rows[:n]))
    (out / "boxes.txt").write_text(BOXES_HEADER + "".join(box_lines))  # last: marks a complete folder
    log.info("make-dynamic: %d KITTI frames, %d people -> %s", n, cfg.n_people, out)
    return out


def _make_dynamic_tum(seq_dir: str | Path, out_dir: str | Path, coco_root: str | Path, cfg: MakeDynamicConfig,
                      progress: Progress | None = None) -> Path:
    import shutil

    from vslam.data.synthetic.writer import depth_to_png
    from vslam.data.tum import TumRgbdSequence

    seq = TumRgbdSequence(seq_dir)
    cam = seq.calibration.cam0
    total = len(seq) if cfg.max_frames is None else min(len(seq), cfg.max_frames)
    out = Path(out_dir)
    for sub in ("rgb", "depth", "mask"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, mask_lines, box_lines = [], [], [], []
    for fr, img, depth, mask, boxes in composited_frames(seq_dir, coco_root, cfg):
        stamp = f"{fr.timestamp:.6f}"
        box_lines += _box_lines(stamp, boxes)
        cv2.imwrite(str(out / "rgb" / f"{stamp}.png"), img)
        cv2.imwrite(str(out / "depth" / f"{stamp}.png"), depth_to_png(depth))
        cv2.imwrite(str(out / "mask" / f"{stamp}.png"), mask.astype(np.uint8) * 255)
        rgb_lines.append(f"{stamp} rgb/{stamp}.png\n")
        depth_lines.append(f"{stamp} depth/{stamp}.png\n")
        mask_lines.append(f"{stamp} mask/{stamp}.png\n")
        if progress is not None:
            progress(len(rgb_lines), total)
    header = "# vslam make-dynamic: {} composited from {}\n# timestamp filename\n"
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines), ("mask.txt", mask_lines)):
        (out / name).write_text(header.format(name, seq_dir) + "".join(lines))
    shutil.copy(Path(seq_dir) / "groundtruth.txt", out / "groundtruth.txt")
    (out / "calibration.yaml").write_text(f"width: {cam.width}\nheight: {cam.height}\nfx: {cam.fx!r}\nfy: {cam.fy!r}\n"
                                          f"cx: {cam.cx!r}\ncy: {cam.cy!r}\ndistortion_model: none\ndistortion: []\n"
                                          f"depth_scale: 5000.0\n")
    (out / "boxes.txt").write_text(BOXES_HEADER + "".join(box_lines))  # last: marks a complete folder
    log.info("make-dynamic: %d frames, %d people -> %s", len(rgb_lines), cfg.n_people, out)
    return out


def walker_config(data: Path, people: int | None, seed: int, max_frames: int | None = None) -> MakeDynamicConfig:
    """The walkers for ``data``: indoor ones for TUM, road crossers for KITTI."""
    from vslam.data.kitti import is_kitti_layout

    if is_kitti_layout(data):
        return MakeDynamicConfig.for_kitti(6 if people is None else people, seed, max_frames)
    return MakeDynamicConfig(n_people=3 if people is None else people, seed=seed, max_frames=max_frames)
