"""Configuration of the synthetic sequence generator.

Plain field types only (numbers, bools, strings, tuples, the ``ImuNoise``
dataclass) so that a YAML file fills it through ``vslam.config.from_dict``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from vslam.data.types import ImuNoise
from vslam.errors import ConfigError

SceneKind = Literal["room", "street", "corridor"]

# Mean camera speed per scene when ``speed`` is left unset: walking pace in a
# room, slow driving in a street.
DEFAULT_SPEED: dict[str, float] = {"room": 0.5, "street": 5.0, "corridor": 0.8}


@dataclass(frozen=True)
class SyntheticConfig:
    """Everything that defines one synthetic sequence; the same config gives byte-identical data.

    Geometry and time: metres, seconds, radians. Pixel conventions follow
    ``PinholeCamera``: integer pixel coordinates are pixel centres.
    """

    scene: SceneKind = "room"
    n_frames: int = 300
    fps: float = 30.0
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    # None: the image centre, (width - 1) / 2 and (height - 1) / 2 (319.5, 239.5 at 640x480).
    cx: float | None = None
    cy: float | None = None
    seed: int = 0
    # Independently moving textured boxes (people-sized, 0.5 x 0.5 x 1.7 m) walking on the floor.
    n_movers: int = 3
    # Right camera offset along the cam0 +x axis, metres.
    baseline: float = 0.1
    imu_rate: float = 200.0  # Hz; overrides imu_noise.rate_hz
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    # False: measurements are truth + the constant initial biases (no white noise, no bias walk).
    imu_noise_enabled: bool = True
    gyro_bias: tuple[float, float, float] = (0.002, -0.0015, 0.001)  # rad/s, body frame, at the first sample
    accel_bias: tuple[float, float, float] = (0.04, -0.03, 0.02)  # m/s^2, body frame, at the first sample
    # Smooth global gain / gamma variation over time (auto-exposure drift).
    lighting_change: bool = False
    # Most faces nearly flat with a few features (texture-poor corridors, blank walls).
    low_texture: bool = False
    # True: a closed path traversed more than once; False: a path that does not return to its start.
    loop: bool = False
    # (start_frame, length) pairs; those frames are all zeros (image, right image and depth).
    blackouts: tuple[tuple[int, int], ...] = ()
    # (start_frame, length) pairs; those frames' images (left and right, not depth) are Gaussian-blurred
    # with std blur_sigma pixels (defocus / strong motion blur: few, displaced corners).
    blurs: tuple[tuple[int, int], ...] = ()
    blur_sigma: float = 3.0
    # (start_frame, length) pairs; those frames' images (left and right, not depth) keep only fade_contrast of
    # their contrast around their mean grey level (blank walls under flat light: too faint for corners).
    fades: tuple[tuple[int, int], ...] = ()
    fade_contrast: float = 0.1
    # corridor scene: metres from the last camera position to the end wall ahead. The default keeps it out of
    # any depth sensor's range (four walls parallel to the motion: depth alone cannot measure it); a few metres
    # make a dead end that depth ICP can register against (vslam.tracking.dense).
    corridor_end: float = 25.0
    # Poor light (seed 003 ch. 3: lines hold where points fail): the rendered radiance is scaled by ``exposure``
    # (< 1: a dim scene at a fixed sensor gain), then sensor read noise of std ``image_noise`` grey levels is
    # added to every pixel of both cameras, independently per frame (seeded), before rounding to 8 bits. A dim,
    # noisy image moves and drops corners (ORB responds to single pixels) while a long edge's position is
    # still averaged over hundreds of pixels. Depth is not affected.
    exposure: float = 1.0
    image_noise: float = 0.0
    # Mean camera speed, m/s; None: 0.5 in the room, 5.0 in the street.
    speed: float | None = None
    # Black dots on white discs at known world points (``SyntheticSequence.landmarks``).
    markers: bool = True
    # From this frame on (0: never) the camera goes on along its route in another room: the same box and route,
    # other textures and movers (the scene of seed + 1). Places it passes again look alike in shape only: a
    # sequence that must not be merged into one map (two data sets played one after the other).
    second_room: int = 0
    # Time of frame 0, seconds. Large enough that nanosecond stamps (> 1e12) are
    # recognised as nanoseconds by readers that guess the unit.
    start_time: float = 10000.0

    def __post_init__(self) -> None:
        if self.scene not in ("room", "street", "corridor"):
            raise ConfigError(f"synthetic.scene must be 'room', 'street' or 'corridor', got {self.scene!r}")
        if self.scene == "corridor" and self.loop:
            raise ConfigError("synthetic.loop is not available in the corridor scene (a straight walk)")
        checks = {
            "n_frames": self.n_frames >= 1,
            "fps": self.fps > 0,
            "width": self.width >= 8,
            "height": self.height >= 8,
            "fx": self.fx > 0,
            "fy": self.fy > 0,
            "n_movers": 0 <= self.n_movers <= 16,
            "baseline": self.baseline >= 0,
            "imu_rate": self.imu_rate > 0,
            "speed": self.speed is None or self.speed > 0,
            "blur_sigma": self.blur_sigma > 0,
            "fade_contrast": 0 <= self.fade_contrast <= 1,
            "corridor_end": self.corridor_end > 0,
            "exposure": 0 < self.exposure <= 4,
            "image_noise": 0 <= self.image_noise <= 64,
            "second_room": 0 <= self.second_room < self.n_frames,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"synthetic.{name} is out of range: {getattr(self, name)!r}")
        for name in ("blackouts", "blurs", "fades"):
            for i, pair in enumerate(getattr(self, name)):
                if len(pair) != 2 or pair[0] < 0 or pair[1] < 0:
                    raise ConfigError(f"synthetic.{name}[{i}] must be (start_frame >= 0, length >= 0), got {pair!r}")

    @property
    def principal_point(self) -> tuple[float, float]:
        """(cx, cy) pixels with the image-centre defaults resolved."""
        cx = (self.width - 1) / 2.0 if self.cx is None else float(self.cx)
        cy = (self.height - 1) / 2.0 if self.cy is None else float(self.cy)
        return cx, cy

    @property
    def mean_speed(self) -> float:
        """Mean camera speed, m/s, with the per-scene default resolved."""
        return DEFAULT_SPEED[self.scene] if self.speed is None else float(self.speed)

    @property
    def duration(self) -> float:
        """Seconds covered by the frames: n_frames / fps (the last frame is at duration - 1/fps)."""
        return self.n_frames / self.fps


# Fixed scene dimensions (world frame: z up, metres). The room is the interior
# of this box; the street's length follows the camera path (see scene.py).
ROOM_LO: tuple[float, float, float] = (-4.0, -3.0, 0.0)
ROOM_HI: tuple[float, float, float] = (4.0, 3.0, 3.0)
STREET_HALF_WIDTH = 6.0  # facades at y = +-6 m
STREET_HEIGHT = 10.0  # sky "ceiling" at z = 10 m
CAMERA_HEIGHT = 1.5  # nominal body height above the floor, metres
