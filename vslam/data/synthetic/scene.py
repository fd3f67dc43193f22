"""Scene geometry of the synthetic sequences: a textured static box seen from inside, plus movers.

Faces of an axis-aligned box are numbered f = 2*k + side: k the normal axis
(0 x, 1 y, 2 z), side 0 the plane at ``lo[k]``, 1 the plane at ``hi[k]``.
A face's 2-D texture coordinates (s, r) are metres from the box's ``lo``
corner along the axes ``FACE_AXES[k]``. All textures live in one atlas image
so the renderer samples every face with a single ``cv2.remap``.

"street" faces are long: their textures are rows of 12 m tiles, each a copy
of one of four seeded variants, so generation stays fast while neighbouring
tiles differ; the rows are laid out in full in the atlas so the renderer
needs no per-pixel tiling.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from vslam.data.synthetic import corridor, textures
from vslam.data.synthetic.config import ROOM_HI, ROOM_LO, STREET_HALF_WIDTH, STREET_HEIGHT, SyntheticConfig

logger = logging.getLogger(__name__)

FACE_AXES = ((1, 2), (0, 2), (0, 1))  # (s axis, r axis) for normal axis k
MAX_STRIP = 32000  # texels: cv2.remap addresses the atlas with int16 coordinates
PAD = 1  # texels of border around each atlas patch so bilinear sampling never reads a neighbour
PERSON_SIZE = (0.5, 0.5, 1.7)
CLEARANCE = 0.6  # metres between a mover's box and any camera centre, at every frame


@dataclass(frozen=True, eq=False)
class Mover:
    """Axis-aligned box whose centre moves as
    centre + vel*tau + amp*(u1*sin(omega*tau + phase) + u2*cos(omega*tau + phase)).

    u2 = 0 gives a back-and-forth walk along u1, u2 orthogonal to u1 a circle.
    face_x, face_y: (6,) atlas position of texel (0,0) of each face's patch.
    """

    size: np.ndarray
    centre: np.ndarray
    vel: np.ndarray
    u1: np.ndarray
    u2: np.ndarray
    amp: float
    omega: float
    phase: float
    face_x: np.ndarray = field(default_factory=lambda: np.zeros(6))
    face_y: np.ndarray = field(default_factory=lambda: np.zeros(6))

    def centre_at(self, tau: np.ndarray) -> np.ndarray:
        """(N,) s -> (N,3) world box centres."""
        tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))[:, None]
        arg = self.omega * tau + self.phase
        return self.centre + self.vel * tau + self.amp * (self.u1 * np.sin(arg) + self.u2 * np.cos(arg))

    def bounds(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) world corners (3,) at one time."""
        c = self.centre_at(np.array([tau]))[0]
        return c - self.size / 2, c + self.size / 2


@dataclass(eq=False)
class Scene:
    """Static box (lo, hi), texture atlas and movers.

    ppm: texels per metre of every face. face_x, face_y: (6,) atlas position of
    texel (0,0) of each static face. landmarks: (M,3) world centres of the markers.
    """

    kind: str
    lo: np.ndarray
    hi: np.ndarray
    ppm: float
    atlas: np.ndarray
    face_x: np.ndarray
    face_y: np.ndarray
    movers: list[Mover]
    landmarks: np.ndarray


@dataclass(frozen=True, eq=False)
class _Strip:
    """A street face's texture as what it is made of -- ``order`` (n,) picks a variant (h, w_tile, 3) uint8 per tile,
    cut at ``width`` texels -- so the full row of tiles exists only once, in the atlas."""

    variants: list[np.ndarray]
    order: np.ndarray
    width: int

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.variants[0].shape[0], self.width, 3

    def paint(self, dst: np.ndarray) -> None:
        """Write the strip into ``dst`` (h, width, 3)."""
        w_tile = self.variants[0].shape[1]
        for n, v in enumerate(self.order):
            x0 = n * w_tile
            if x0 >= self.width:
                break
            x1 = min(x0 + w_tile, self.width)
            dst[:, x0:x1] = self.variants[v][:, : x1 - x0]


class _AtlasBuilder:
    """Shelf-packs padded patches into one image (rows of patches, left to right).

    Patches are kept as given and painted once, into the final image (no padded copies): a long street's
    atlas is hundreds of MB, and each copy of it would add to the peak memory of whichever process builds it.
    """

    def __init__(self, width: int = 4096):
        self.width = width
        self.patches: list[tuple[int, int, np.ndarray | _Strip]] = []
        self.x = self.y = self.row_h = 0

    def add(self, img: np.ndarray | _Strip) -> tuple[float, float]:
        """Place a patch; returns the atlas (x, y) of its texel (0,0)."""
        h, w = img.shape[0] + 2 * PAD, img.shape[1] + 2 * PAD
        if self.x + w > self.width:
            self.x, self.y, self.row_h = 0, self.y + self.row_h, 0
        self.patches.append((self.x, self.y, img))
        pos = (float(self.x + PAD), float(self.y + PAD))
        self.x += w
        self.row_h = max(self.row_h, h)
        return pos

    def build(self) -> np.ndarray:
        height = self.y + self.row_h
        width = max(x + p.shape[1] + 2 * PAD for x, _, p in self.patches)
        if max(width, height) >= 32767:  # cv2.remap stores coordinates as int16
            raise ValueError(f"texture atlas {width}x{height} exceeds cv2.remap's 32767 limit; lower ppm")
        atlas = np.zeros((height, width, 3), np.uint8)
        for x, y, p in self.patches:
            h, w = p.shape[:2]
            inner = atlas[y + PAD : y + PAD + h, x + PAD : x + PAD + w]
            if isinstance(p, _Strip):
                p.paint(inner)
            else:
                inner[:] = p
            # the border repeats the edge texels (cv2.BORDER_REPLICATE): bilinear sampling at an edge never
            # reads a neighbour
            rows = slice(y + PAD, y + PAD + h)
            atlas[rows, x : x + PAD] = inner[:, :1]
            atlas[rows, x + PAD + w : x + 2 * PAD + w] = inner[:, -1:]
            atlas[y : y + PAD, x : x + w + 2 * PAD] = atlas[y + PAD, x : x + w + 2 * PAD]
            atlas[y + PAD + h : y + 2 * PAD + h, x : x + w + 2 * PAD] = atlas[y + PAD + h - 1, x : x + w + 2 * PAD]
        return atlas


def _face_size(lo: np.ndarray, hi: np.ndarray, f: int) -> tuple[float, float]:
    sa, ra = FACE_AXES[f // 2]
    return float(hi[sa] - lo[sa]), float(hi[ra] - lo[ra])


def _face_point(lo: np.ndarray, hi: np.ndarray, f: int, s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(M,) face coordinates -> (M,3) world points on face f."""
    k = f // 2
    sa, ra = FACE_AXES[k]
    pts = np.zeros((len(s), 3))
    pts[:, k] = hi[k] if f % 2 else lo[k]
    pts[:, sa] = lo[sa] + s
    pts[:, ra] = lo[ra] + r
    return pts


def _room_faces(cfg: SyntheticConfig, rng: np.random.Generator) -> list[str]:
    if not cfg.low_texture:
        return ["rich"] * 6
    kinds = ["flat"] * 6
    kinds[int(rng.integers(0, 4))] = "rich"  # one wall keeps its texture: "most walls nearly flat"
    return kinds


def _make_patch(kind: str, rng: np.random.Generator, size: tuple[float, float], ppm: float, low: bool) -> np.ndarray:
    w, h = int(np.ceil(size[0] * ppm - 1e-6)), int(np.ceil(size[1] * ppm - 1e-6))
    makers = {
        "rich": lambda: textures.rich(rng, h, w, ppm),
        "flat": lambda: textures.flat(rng, h, w, ppm),
        "facade": lambda: textures.facade(rng, h, w, ppm, low),
        "ground": lambda: textures.ground(rng, h, w, ppm, low),
        "sky": lambda: textures.sky(rng, h, w, ppm),
    }
    return makers[kind]()


def build_scene(cfg: SyntheticConfig, cam_positions: np.ndarray, frame_tau: np.ndarray) -> Scene:
    """The static box, its textures and movers for ``cfg``.

    cam_positions: (N,2,3) world centres of cam0 and cam1 at the frame times
    ``frame_tau`` (N,) s; the street's length follows them and movers keep
    CLEARANCE from them.
    """
    rng = np.random.default_rng([cfg.seed, 3])  # stream 3: scene and textures
    if cfg.scene == "corridor":  # plain walls with long edges (corridor.py); no markers, no movers
        lo, hi = corridor.corridor_box(cam_positions, cfg.corridor_end)
        images = corridor.face_textures(rng, [_face_size(lo, hi, f) for f in range(6)], corridor.CORRIDOR_PPM)
        atlas = _AtlasBuilder(max(4096, max(img.shape[1] for img in images) + 2 * PAD))
        pos = np.array([atlas.add(img) for img in images])
        if cfg.n_movers:
            logger.warning("synthetic: the corridor scene has no movers; n_movers=%d ignored", cfg.n_movers)
        return Scene(cfg.scene, lo, hi, corridor.CORRIDOR_PPM, atlas.build(), pos[:, 0], pos[:, 1], [], np.zeros((0, 3)))
    if cfg.scene == "room":
        lo, hi, ppm, tile = np.array(ROOM_LO), np.array(ROOM_HI), 200.0, 0.0
        kinds = _room_faces(cfg, rng)
        style = textures.MarkerStyle(0.03, 0.09, 2.0 if cfg.low_texture else 1.0)
    else:
        x0, x1 = cam_positions[..., 0].min(), cam_positions[..., 0].max()
        lo = np.array([x0 - 30.0, -STREET_HALF_WIDTH, 0.0])
        hi = np.array([max(x0 + 170.0, x1 + 60.0), STREET_HALF_WIDTH, STREET_HEIGHT])
        ppm, tile = 60.0, 12.0
        if (hi[0] - lo[0]) * ppm > MAX_STRIP:
            ppm = MAX_STRIP / (hi[0] - lo[0])
            tile = np.ceil(12.0 * ppm) / ppm  # whole texels per tile keep the tiles seamless
            logger.warning("synthetic: %.0f m street; textures coarsened to %.1f texels/m", hi[0] - lo[0], ppm)
        kinds = ["facade", "facade", "facade", "facade", "ground", "sky"]
        style = textures.MarkerStyle(0.1, 0.3, 6.0 if cfg.low_texture else 3.0)
    images, landmarks = [], []
    for f in range(6):
        tiled = tile > 0 and f // 2 != 0  # street: every face but the two end walls
        img, mk = _face_texture(cfg, rng, kinds[f], _face_size(lo, hi, f), ppm, tile if tiled else 0.0, style)
        images.append(img)
        landmarks.append(_face_point(lo, hi, f, mk[:, 0], mk[:, 1]))
    atlas = _AtlasBuilder(max(4096, max(img.shape[1] for img in images) + 2 * PAD))
    pos = np.array([atlas.add(img) for img in images])
    movers = _place_movers(cfg, rng, lo, hi, cam_positions, frame_tau, atlas, ppm)
    return Scene(cfg.scene, lo, hi, ppm, atlas.build(), pos[:, 0], pos[:, 1], movers, np.concatenate(landmarks))


def _face_texture(
    cfg: SyntheticConfig, rng: np.random.Generator, kind: str, size: tuple[float, float], ppm: float, tile: float,
    style: textures.MarkerStyle,
) -> tuple[np.ndarray | _Strip, np.ndarray]:
    """Texture of a face of ``size`` (s, r) metres and its markers (M,2) in face metres.

    tile > 0: the face is a row of tiles, each a copy of one of 4 seeded variants,
    so a 200 m street costs 4 tiles of generation and neighbouring tiles differ
    (a ``_Strip``: the row is laid out only in the atlas).
    """
    with_markers = cfg.markers and kind != "sky"
    n_var = 4 if tile > 0 else 1
    variants, markers = [], []
    for _ in range(n_var):
        img = _make_patch(kind, rng, (tile, size[1]) if tile > 0 else size, ppm, cfg.low_texture)
        markers.append(textures.draw_markers(rng, img, ppm, style) if with_markers else np.zeros((0, 2)))
        variants.append(img)
    if tile <= 0:
        return variants[0], markers[0]
    order = rng.integers(0, n_var, int(np.ceil(size[0] / tile)))
    strip = _Strip(variants, order, min(len(order) * variants[0].shape[1], int(np.ceil(size[0] * ppm))))
    mk = np.concatenate([markers[v] + (n * tile, 0.0) for n, v in enumerate(order)])
    return strip, mk[mk[:, 0] <= size[0] - style.r_out]


def _candidate_mover(cfg: SyntheticConfig, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, x_range: tuple[float, float]) -> Mover:
    """One random walking person: along a wall or on a circle (room), along a sidewalk (street)."""
    size = np.array(PERSON_SIZE)
    zero = np.zeros(3)
    if cfg.scene == "street":
        side = rng.choice([-1.0, 1.0])
        y = side * rng.uniform(4.3, STREET_HALF_WIDTH - 0.5)
        centre = np.array([rng.uniform(x_range[0] - 5.0, x_range[1] + 30.0), y, size[2] / 2])
        vel = np.array([rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.6), 0.0, 0.0])
        return Mover(size, centre, vel, np.array([0.0, 1.0, 0.0]), zero, 0.15, rng.uniform(1.5, 2.5), rng.uniform(0, 2 * np.pi))
    speed = rng.uniform(0.5, 1.2)
    if rng.uniform() < 0.3:  # circle between the camera path and the walls
        radius = rng.uniform(0.6, 1.2)
        c = rng.uniform(lo[:2] + radius + 0.5, hi[:2] - radius - 0.5)
        centre = np.array([c[0], c[1], size[2] / 2])
        return Mover(size, centre, zero, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), radius, speed / radius, rng.uniform(0, 2 * np.pi))
    wall = int(rng.integers(0, 4))  # walk back and forth along a wall
    k, along = (0, 1) if wall < 2 else (1, 0)
    centre = np.zeros(3)
    d = rng.uniform(0.35, 1.2)
    centre[k] = lo[k] + d if wall % 2 == 0 else hi[k] - d
    span = hi[along] - lo[along] - 1.0
    amp = rng.uniform(0.6, span / 2 - 0.2)
    centre[along] = rng.uniform(lo[along] + 0.5 + amp, hi[along] - 0.5 - amp)
    centre[2] = size[2] / 2
    u1 = np.zeros(3)
    u1[along] = 1.0
    return Mover(size, centre, zero, u1, zero, amp, speed / amp, rng.uniform(0, 2 * np.pi))


def _clear(m: Mover, others: list[Mover], cams: np.ndarray, tau: np.ndarray) -> bool:
    """True when m keeps CLEARANCE from every camera centre and does not touch another mover."""
    c = m.centre_at(tau)
    gap = np.abs(cams - c[:, None, :]) - m.size / 2  # (N, cams, 3) per-axis gap to the box
    if np.any(np.all(gap < CLEARANCE, axis=-1)):
        return False
    for o in others:
        if np.any(np.all(np.abs(o.centre_at(tau) - c) < (o.size + m.size) / 2 + 0.1, axis=-1)):
            return False
    return True


def _place_movers(
    cfg: SyntheticConfig, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray,
    cams: np.ndarray, tau: np.ndarray, atlas: _AtlasBuilder, ppm: float,
) -> list[Mover]:
    """cfg.n_movers movers by rejection sampling; each gets its own six texture patches."""
    x_range = (float(cams[..., 0].min()), float(cams[..., 0].max()))
    movers: list[Mover] = []
    for i in range(cfg.n_movers):
        for _ in range(200):
            m = _candidate_mover(cfg, rng, lo, hi, x_range)
            if _clear(m, movers, cams, tau):
                break
        else:
            logger.warning("synthetic: no clear path for mover %d of %d; the scene has fewer movers", i + 1, cfg.n_movers)
            continue
        fx, fy = np.zeros(6), np.zeros(6)
        for f in range(6):
            s_len, r_len = _face_size(np.zeros(3), m.size, f)
            img = textures.mover(rng, int(np.ceil(r_len * ppm)), int(np.ceil(s_len * ppm)), ppm)
            fx[f], fy[f] = atlas.add(img)
        movers.append(Mover(m.size, m.centre, m.vel, m.u1, m.u2, m.amp, m.omega, m.phase, fx, fy))
    return movers
