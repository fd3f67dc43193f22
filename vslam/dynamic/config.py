"""Settings of dynamic-object filtering: which keypoints are dropped before tracking and mapping."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from vslam.errors import ConfigError

MaskSource = Literal["detector", "gt_mask", "none"]
MaskShape = Literal["instance", "box"]


@dataclass(frozen=True)
class GeometricConfig:
    """DynaSLAM-style motion check (no network): a keypoint whose world point, back-projected with its depth and
    the tracked pose, disagrees with the world point of the same feature a few frames earlier is moving.

    A keypoint is flagged when the 3-D residual exceeds ``abs_m + rel * depth`` against at least ``min_votes`` of
    the frames ``frame_gaps`` back (several frames: one mismatched descriptor or one noisy depth cannot flag it).
    Flagged keypoints spread to neighbours within ``region_px`` pixels and ``region_depth_m`` depth (the moving
    object, like DynaSLAM's depth region growing); that region is also removed from the next frame before
    tracking.
    """

    enabled: bool = False
    frame_gaps: tuple[int, ...] = (3, 6, 9)
    min_votes: int = 2
    abs_m: float = 0.03  # metres: depth noise + pose error of a static point
    rel: float = 0.01  # fraction of the depth (RGB-D depth noise grows with range)
    max_hamming: int = 50  # binary descriptors: a match further than this is ignored
    max_l2: float = 0.7  # float descriptors
    edge_m: float = 0.0  # > 0: no check where the depth within 2 px spans more than this (+ rel * depth):
    # a keypoint on a depth edge (ORB corners sit on outlines) reads fore- or background depth by a pixel
    region_px: float = 25.0
    region_depth_m: float = 0.3
    min_depth: float = 0.1
    max_depth: float = 10.0
    # detector boxes: a box whose keypoints were compared against min_votes past frames (at least
    # static_min_points of them) and of which at most static_max_moving flagged motion holds a static instance
    # (a sitting person, or a false detection: the teddy bear read as a person); overlapping boxes of the next
    # frames (IoU >= 0.5) are then not masked while the verdict holds, and their moving keypoints still are
    keep_static_boxes: bool = False
    static_min_points: int = 8
    static_max_moving: float = 0.1
    moving_memory_s: float = 5.0  # a box that overlaps one of an object seen moving this recently stays masked
    # False: the check only judges detector boxes (keep_static_boxes) and flags no keypoint itself. A COCO
    # detector's false boxes on static things (YOLOX-nano's person box over TUM's teddy bear) are then released,
    # without the check's own false flags on static points, which cost accuracy beside a detector
    flag_points: bool = True

    def __post_init__(self) -> None:
        if self.static_min_points < 1 or not 0 <= self.static_max_moving < 1 or self.moving_memory_s < 0:
            raise ConfigError("slam.dynamic.geometric: static_min_points must be >= 1, static_max_moving in [0, 1) and "
                              "moving_memory_s >= 0")
        if not self.flag_points and not self.keep_static_boxes:
            raise ConfigError("slam.dynamic.geometric.flag_points=false leaves the check only its box verdicts: "
                              "set keep_static_boxes=true (or disable the check)")
        if not self.frame_gaps or min(self.frame_gaps) < 1:
            raise ConfigError("slam.dynamic.geometric.frame_gaps must be a non-empty list of gaps >= 1")
        if not 1 <= self.min_votes <= len(self.frame_gaps):
            raise ConfigError(f"slam.dynamic.geometric.min_votes must be in 1..{len(self.frame_gaps)}")


@dataclass(frozen=True)
class DynamicConfig:
    """``source``: where the masks of dynamic objects come from. ``gt_mask`` uses the synthetic generator's exact
    masks (an oracle that bounds what masking can give); ``detector`` runs the attention detector and masks the
    instances (``mask``) or boxes of ``classes``; ``none`` masks nothing (geometric check only, when enabled)."""

    enabled: bool = False
    source: MaskSource = "gt_mask"
    classes: tuple[str, ...] = ("person", "bicycle", "car", "motorcycle", "bus", "truck", "chair")
    dilation_px: int = 4  # mask / box growth: keypoints on an object's outline have an ORB patch on it
    # detector: what a detection masks. "instance": its instance mask (dilated by dilation_px), so the static
    # pixels its box holds beside the object stay trackable; a detection without a mask (weights without a mask
    # head, a mask covering less than mask_min_fill of its box) masks its box. "box": always the box.
    mask: MaskShape = "instance"
    mask_min_fill: float = 0.2  # an instance mask that covers less of its box is not trusted: the box is masked
    # instance masks grow by this many of their prototype cells (Detections.mask_px) before dilation_px: a mask
    # assembled at 1/4 of the network's input has outlines uncertain by about half a cell (~5 px for a 640x480
    # frame at the shipped 256 px input), and ORB corners sit on outlines
    mask_grow_cells: float = 0.5
    # detector boxes below this score are ignored. The threshold belongs to the weights: set it with them (KITTI's
    # round 4 at 0.2, bench row kitti07-people-mono-detector). 0.15 for the shipped SE model: best mean and worst
    # ATE on the twelve TUM validation composites (docs/dynamic.md).
    score_threshold: float = 0.15
    # detector: the boxes of the frames of the last ``box_memory_s`` seconds are masked too (a person missed in
    # one frame was found in one before; boxes move little in a fraction of a second). Chosen on a validation
    # composite (docs/dynamic.md, 'Measurements behind settings in the code')
    box_memory_s: float = 0.27
    # the box memory holds only objects detected in at least this many frames of its window (the box overlapping,
    # IoU >= 0.3, one of each earlier frame's boxes); a detection seen once is masked in its own frame only. 2
    # keeps a one-frame false box over a large static object (YOLOX-nano's low-score person box on TUM's teddy
    # bear) from blanking the scene for the whole window. 1 (every box held): 2 did not beat it on the validation
    # composites with the shipped detector (docs/dynamic.md, 'Measurements behind settings in the code').
    box_memory_min_hits: int = 1
    # detector boxes also grow by this fraction of their size on each side: a small model's box edges are off by
    # ~ a stride of its coarsest level, and a limb or a foot just outside the box leaks keypoints. Off: the
    # shipped detector boxes generously enough that growing cost accuracy on the validation composites
    # (docs/dynamic.md, 'Measurements behind settings in the code')
    box_grow: float = 0.0
    # detector: run it on every n-th frame only (frame index divisible by n); the frames between mask the last
    # detection's boxes (and the box memory), which saves (n-1)/n of the network's cost. But a held box misses a
    # mover's leading edge, which costs accuracy where the camera moves fast. Hence 1 (docs/dynamic.md,
    # 'Measurements behind settings in the code')
    detect_every: int = 1
    # detector: a box the detector stops finding is followed for up to this many seconds by the median motion of
    # the keypoints matched inside it from the previous frame (MedianFlow-like; the detector's box replaces it
    # when one overlaps it again, IoU >= 0.3). 0 = off: box memory alone holds a missed box where it was.
    # Off: it helped the validation composites but made the held-out composites' two failures worse; a longer
    # box memory did not help either (docs/dynamic.md).
    box_track_s: float = 0.0
    box_track_min_matches: int = 6  # fewer matches inside a followed box: it stays where it was this frame
    weights: str = ""  # detector checkpoint (source=detector); "" = the shipped vslam/models/detector_se_seg.pt
    # more detector checkpoints whose boxes are masked too (an ensemble: the union of their boxes, each network
    # costs its own time). Recall is what masking needs: a person the detector misses leaks keypoints into the
    # map, and on TUM teddy composites with a close-up walker cut by the frame tracking then follows the walker.
    # An SE + ESEA pair beat either alone on the validation and held-out composites. Off by default: the mask
    # step's network time doubles (docs/dynamic.md, 'Measurements behind settings in the code')
    extra_weights: tuple[str, ...] = ()
    img_size: int = 0  # detector input: the image's longer side resized to this; 0 = the size it was trained at
    # YOLOX-style detectors: keep the frame's aspect (img_size its longer side, the shorter one rounded up to a
    # multiple of 32) instead of the square input they were trained at; a street frame squashed into a square
    # loses its people (KITTI 1241x376 at 1248 runs at 1248x384). The from-scratch detector always keeps it.
    wide: bool = False
    device: str = "auto"  # detector: auto = CUDA when torch sees a GPU (same boxes up to float rounding), cpu, cuda
    geometric: GeometricConfig = field(default_factory=GeometricConfig)

    def __post_init__(self) -> None:
        if self.source not in ("detector", "gt_mask", "none"):
            raise ConfigError(f"slam.dynamic.source must be detector, gt_mask or none, got {self.source!r}")
        if self.mask not in ("instance", "box"):
            raise ConfigError(f"slam.dynamic.mask must be instance or box, got {self.mask!r}")
        if not 0 <= self.mask_min_fill <= 1:
            raise ConfigError(f"slam.dynamic.mask_min_fill must be in [0, 1], got {self.mask_min_fill}")
        if self.mask_grow_cells < 0:
            raise ConfigError(f"slam.dynamic.mask_grow_cells must be >= 0, got {self.mask_grow_cells}")
        if self.dilation_px < 0:
            raise ConfigError("slam.dynamic.dilation_px must be >= 0")
        if not 0 <= self.box_grow <= 1:
            raise ConfigError(f"slam.dynamic.box_grow must be in [0, 1], got {self.box_grow}")
        if self.detect_every < 1:
            raise ConfigError(f"slam.dynamic.detect_every must be >= 1, got {self.detect_every}")
        if self.box_memory_s < 0 or self.box_memory_min_hits < 1:
            raise ConfigError(f"slam.dynamic: box_memory_s must be >= 0 and box_memory_min_hits >= 1, got "
                              f"{self.box_memory_s} and {self.box_memory_min_hits}")
        if self.box_track_s < 0 or self.box_track_min_matches < 1:
            raise ConfigError(f"slam.dynamic: box_track_s must be >= 0 and box_track_min_matches >= 1, got "
                              f"{self.box_track_s} and {self.box_track_min_matches}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"slam.dynamic.device must be auto, cpu or cuda, got {self.device!r}")
        if self.img_size < 0 or self.img_size % 32:
            raise ConfigError(f"slam.dynamic.img_size must be 0 or a positive multiple of 32, got {self.img_size}")
