"""Omnidirectional simulator: a room, a route, a hyperboloidal-mirror camera, odometry, ground truth.

Output (a drive log v1 with ``[camera] model = "omni"``, :mod:`pipeline.drivelog`)::

    OUT/drive.toml, frames.csv, odometry.csv, ground_truth.csv   (write_drive_log; drive.toml
                                   has [route] id: the route kind, PREV's id for --world PREV,
                                   or --route-id)
    OUT/images/000000.png ...      raw omni frames (image circle, vignetting, noise), 8-bit grey
    OUT/world/world.json           room, objects, lamps, windows, texture regions, provenance
    OUT/world/atlas.png            every surface texture in one raster (uint16, grey x 256)
    OUT/world/route.csv            the nominal (memorized) route s,x,y,theta a --world run reuses

The world (world frame of :mod:`mapstore.grid`, metres): walls on the rectangle
``[0, room_x] x [0, room_y]`` up to ``wall_height_m`` (the ceiling there), box objects
(vertical prisms: centre, half sizes, yaw, height), a textured floor (the floor simulator's
worn concrete, :func:`pipeline.simulate.texture.procedural_texture`), posters, doors and
windows on the walls, lamp panels on the ceiling. A pose ``(x, y, theta)`` is the position of
the mirror axis on the floor and the heading; the camera's viewpoint is ``height_m`` above it.

Rendering (:class:`OmniRenderer`): every pixel inside the image annulus has its viewing
direction from :meth:`tracker.omnicam.HyperboloidCamera.ray` (the mirror reflection as the
model defines it), computed once. Per frame the directions are turned by the heading and
intersected, vectorized, with the walls, floor and ceiling and with the boxes (each box only
against the pixels whose azimuth range it covers: pixels are sorted by azimuth); the hit
point's texture is sampled from a mip pyramid of the texture atlas at the level the pixel's
footprint asks for (trilinear), shaded by the day or night illumination, then vignetting,
exposure gain, sensor noise and quantization. Odometry and ground truth are written exactly
as the floor simulator writes them (:mod:`pipeline.simulate.odometry`).
"""

from __future__ import annotations

import json
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from mapstore.grid import MapGrid, wrap_angle
from pipeline.progress import progress
from pipeline.config import config_hash
from mapstore.routes import check_route_id
from pipeline.config import read_toml
from pipeline.drivelog import CameraSpec, parse_route_id, write_drive_log
from pipeline.errors import BadInput
from pipeline.fsutil import atomic_dir, write_json_atomic, write_text_atomic
from pipeline.images import write_image
from pipeline.simulate.floor import exposure_gain, parse_pair
from pipeline.simulate.odometry import odometry_times, simulate_odometry
from pipeline.simulate.route import ROUTES, Route, from_polyline, make_route
from pipeline.simulate.texture import procedural_texture, smooth_noise
from tracker.omnicam import HyperboloidCamera

__all__ = [
    "OmniOptions",
    "Box",
    "World",
    "resolve_options",
    "camera_from_config",
    "generate_world",
    "load_world",
    "offset_route",
    "horizon_hits",
    "move_objects",
    "OmniRenderer",
    "simulate_omni",
]

WORLD_DIR = "world"
WORLD_FILE = "world.json"
ATLAS_FILE = "atlas.png"
ROUTE_FILE = "route.csv"
IMAGES_DIR = "images"
WORLD_FORMAT = "mosaicmap-omni-world"
# The atlas is stored as uint16 grey levels x ATLAS_SCALE (1/256 grey level steps, lossless PNG).
ATLAS_SCALE = 256.0
# The vehicle's radius (metres) that must stay clear of walls and objects.
BODY_RADIUS_M = 0.15
# cv2.remap refuses sources of SHRT_MAX pixels or more per side (OpenCV limit).
_MAX_ATLAS_SIDE = 32766
_ATLAS_ROW_WIDTH = 8192
# Independent random streams, spawned from the seed in this order (do not reorder).
_STREAMS = ("texture", "objects", "route", "odometry", "exposure", "frames", "move")
# Surface codes of the renderer.
_FLOOR, _CEILING, _WALL = 0, 1, 2


# --- options -----------------------------------------------------------------------------


@dataclass(frozen=True)
class OmniOptions:
    """The effective, validated options of one simulation (units in the names)."""

    seed: int
    room_m: tuple[float, float]
    route: str
    world: str  # previous log path, "" for a fresh world
    night: bool
    height_offset_m: float
    move_objects: float
    offset_m: float
    angle_deg: float
    noise_sigma: float
    odometry_drift: float
    route_id: str


def _num(value, where: str, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BadInput(where, f"must be a finite number, got {value!r}")
    v = float(value)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise BadInput(where, f"must be {'>' if lo_open else '>='} {lo}, got {v}")
    if hi is not None and v >= hi:
        raise BadInput(where, f"must be < {hi}, got {v}")
    return v


def resolve_options(cfg: dict, given: dict) -> OmniOptions:
    """Overlay command-line values ``given`` (None = not given) on ``[simulate.omni]`` and validate.

    Raises :class:`BadInput` naming the option (or configuration key) at fault.
    """
    sim, om = cfg["simulate"], cfg["simulate"]["omni"]

    def pick(opt: str, key: str, table: dict = om, prefix: str = "simulate.omni"):
        v = given.get(opt.replace("-", "_"))
        return (v, f"--{opt}") if v is not None else (table[key], f"config {prefix}.{key}")

    seed = given.get("seed")
    seed, where = (seed, "--seed") if seed is not None else (sim["seed"], "config simulate.seed")
    if given.get("seed") is None and given.get("world"):
        # a repeat run is a new run: the previous log's seed + 1 (the same seed would give
        # the same frames and odometry, a duplicate log)
        seed, where = previous_seed(given["world"]) + 1, "--world (previous log's seed + 1)"
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise BadInput(where, f"must be a non-negative integer, got {seed!r}")
    if given.get("room") is not None:
        room = parse_pair(given["room"], "--room")
    else:
        r = om["room_m"]
        if not (isinstance(r, list) and len(r) == 2 and all(isinstance(v, (int, float)) and v > 0 for v in r)):
            raise BadInput("config simulate.omni.room_m", f"must be two positive numbers, got {r!r}")
        room = (float(r[0]), float(r[1]))
    route, where = pick("route", "route")
    if route not in ROUTES:
        raise BadInput(where, f"unknown route {route!r} (known: {', '.join(ROUTES)})")
    night = bool(given["night"]) if given.get("night") else bool(om["night"])
    v, where = pick("height-offset", "height_offset_m")
    height_offset = _num(v, where)
    h = cfg["simulate"]["omni"]["camera"]["height_m"]
    if not (0.05 < h + height_offset < om["wall_height_m"] - 0.05):
        raise BadInput(where, f"puts the camera at {h + height_offset:.3f} m, outside the room's height "
                              f"(0.05 .. {om['wall_height_m'] - 0.05:.2f} m)")
    v, where = pick("move-objects", "move_objects")
    move = _num(v, where, lo=0.0, hi=1.0)
    v, where = pick("offset", "offset_m")
    offset = _num(v, where)
    v, where = pick("angle", "angle_deg")
    angle = _num(v, where)
    if abs(angle) >= 80.0:
        raise BadInput(where, f"crossing angle must be within +-80 degrees, got {angle}")
    v, where = pick("noise", "noise_sigma", om["sensor"], "simulate.omni.sensor")
    noise = _num(v, where, lo=0.0)
    v, where = pick("odometry-drift", "drift", om["odometry"], "simulate.omni.odometry")
    drift = _num(v, where, lo=0.0, hi=1.0)
    world = given.get("world")
    world = "" if world is None else str(world)
    if world and given.get("room") is not None:
        raise BadInput("--room", "cannot be combined with --world (the world brings its room)")
    if world and given.get("route") is not None:
        raise BadInput("--route", "cannot be combined with --world (a repeat run drives the world's route)")
    route_id = given.get("route_id")
    if route_id is not None:
        try:
            route_id = check_route_id(route_id)
        except ValueError as e:
            raise BadInput("--route-id", str(e)) from None
    elif world:
        route_id = previous_route_id(world)
    else:
        route_id = str(route)
    return OmniOptions(seed, (float(room[0]), float(room[1])), str(route), world, night, height_offset, move,
                       offset, angle, noise, drift, route_id)


def previous_seed(log: str | Path) -> int:
    """The seed a previous simulated log was made with (``[simulation] seed``; 0 if absent)."""
    path = Path(log) / "drive.toml"
    if not path.is_file():
        raise BadInput(log, "--world: previous log directory not found" if not Path(log).is_dir()
                       else "--world: not a drive log (no drive.toml)")
    seed = read_toml(path).get("simulation", {}).get("seed", 0)
    return seed if isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0 else 0


def previous_route_id(log: str | Path) -> str:
    """The route id a ``--world LOG`` run keeps: LOG's ``[route] id``, else the route kind
    it was simulated with (logs written before route ids), else "loop"."""
    path = Path(log) / "drive.toml"
    if not path.is_file():
        raise BadInput(log, "--world: previous log directory not found" if not Path(log).is_dir()
                       else "--world: not a drive log (no drive.toml)")
    meta = read_toml(path)
    rid = parse_route_id(path, meta)
    if rid is not None:
        return rid
    kind = meta.get("simulation", {}).get("options", {}).get("route", "loop")
    return check_route_id(str(kind)) if isinstance(kind, str) else "loop"


def camera_from_config(cam: dict) -> HyperboloidCamera:
    """The simulated hyperboloidal-mirror camera from ``[simulate.omni.camera]``.

    The rim radius is ``rim_radius_frac x min(W, H) / 2`` pixels and sees
    ``rim_elevation_deg``, which fixes the focal length ``f_px``.
    """
    w, h = cam["frame_size"]
    if not (isinstance(w, int) and isinstance(h, int) and min(w, h) >= 16):
        raise BadInput("config simulate.omni.camera.frame_size", f"must be two integers >= 16, got {cam['frame_size']!r}")
    a, b = float(cam["a_m"]), float(cam["b_m"])
    if a <= 0 or b <= 0:
        raise BadInput("config simulate.omni.camera.a_m", "mirror parameters a_m, b_m must be positive")
    half = min(w, h) / 2.0
    rim = float(cam["rim_radius_frac"]) * half
    hole = float(cam["hole_radius_frac"]) * half
    if not 0 <= hole < rim:
        raise BadInput("config simulate.omni.camera.hole_radius_frac", "must be >= 0 and below rim_radius_frac")
    unit = HyperboloidCamera(a, b, 1.0, 0.0, 0.0, float(cam["height_m"]))
    rim_el = math.radians(float(cam["rim_elevation_deg"]))
    if not -math.pi / 2 < rim_el < unit.max_elevation_rad:
        raise BadInput("config simulate.omni.camera.rim_elevation_deg",
                       f"must be below the mirror's limit {math.degrees(unit.max_elevation_rad):.1f} deg")
    f = rim / float(unit.radius_of_elevation(rim_el))
    dx, dy = cam["principal_offset_px"]
    return HyperboloidCamera(a_m=a, b_m=b, f_px=f, cx=(w - 1) / 2.0 + float(dx), cy=(h - 1) / 2.0 + float(dy),
                             height_m=float(cam["height_m"]), rim_radius_px=rim, hole_radius_px=hole)


# --- the world ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Box:
    """A box object: a vertical prism on the floor (metres, radians, world frame).

    ``cx, cy`` centre; ``sx, sy`` half sizes along its local axes; ``yaw`` its rotation;
    ``height``; ``texture``: the name prefix of its atlas regions (``_side``, ``_top``).
    """

    cx: float
    cy: float
    sx: float
    sy: float
    yaw: float
    height: float
    texture: str

    def corners(self) -> np.ndarray:
        """Footprint corners (4, 2), counter-clockwise, world metres."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        local = np.array([[self.sx, self.sy], [-self.sx, self.sy], [-self.sx, -self.sy], [self.sx, -self.sy]])
        return np.stack([self.cx + c * local[:, 0] - s * local[:, 1], self.cy + s * local[:, 0] + c * local[:, 1]], 1)

    def distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Horizontal distance (metres) of world points from the footprint (0 inside)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = np.asarray(x) - self.cx, np.asarray(y) - self.cy
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        return np.hypot(np.maximum(np.abs(lx) - self.sx, 0.0), np.maximum(np.abs(ly) - self.sy, 0.0))

    @property
    def perimeter(self) -> float:
        return 4.0 * (self.sx + self.sy)


@dataclass
class World:
    """The simulated room (see the module docstring); ``atlas`` holds every surface texture.

    Attributes:
        room: (x, y) size in metres; wall_height: metres.
        texel: metres per atlas texel (level 0).
        atlas: float32 grey levels (0..255 scale).
        regions: name -> (col0, row0, width, height) of a surface's texels in the atlas.
        objects: the boxes; lamps: (K, 2) lamp centres (metres); lamp_size: (x, y) metres.
        windows: (s0, s1, z0, z1) on the wall perimeter coordinate (metres) and height.
        meta: provenance (seed, source, moved fraction, ...).
    """

    room: tuple[float, float]
    wall_height: float
    texel: float
    atlas: np.ndarray
    regions: dict
    objects: list
    lamps: np.ndarray
    lamp_size: tuple[float, float]
    windows: list
    meta: dict

    @property
    def perimeter(self) -> float:
        return 2.0 * (self.room[0] + self.room[1])

    def floor_grid(self) -> MapGrid:
        """The floor texture's raster (the atlas region ``floor``), north-up."""
        _, _, w, h = self.regions["floor"]
        return MapGrid(0.0, self.room[1], self.texel, w, h)

    def floor_texture(self) -> np.ndarray:
        """The floor's texture (float32 grey levels) on :meth:`floor_grid`."""
        c0, r0, w, h = self.regions["floor"]
        return self.atlas[r0 : r0 + h, c0 : c0 + w].copy()

    def to_json(self) -> dict:
        return {
            "format": WORLD_FORMAT,
            "room_m": list(self.room),
            "wall_height_m": self.wall_height,
            "texel_m": self.texel,
            "atlas": ATLAS_FILE,
            "atlas_scale": ATLAS_SCALE,
            "regions": {k: list(v) for k, v in self.regions.items()},
            "objects": [asdict(b) for b in self.objects],
            "lamps_m": self.lamps.tolist(),
            "lamp_size_m": list(self.lamp_size),
            "windows": [list(w) for w in self.windows],
            "floor_grid": self.floor_grid().to_attrs(),
            "perimeter_origin": "s = 0 at (0, 0), running along y = 0 towards +x, then counter-clockwise",
            **self.meta,
        }


def _wall_point(world_room: tuple[float, float], s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (x, y) of perimeter coordinate ``s`` (metres, counter-clockwise from (0, 0))."""
    rx, ry = world_room
    s = np.mod(s, 2 * (rx + ry))
    x = np.select([s < rx, s < rx + ry, s < 2 * rx + ry], [s, rx, rx - (s - rx - ry)], 0.0)
    y = np.select([s < rx, s < rx + ry, s < 2 * rx + ry], [0.0, s - rx, ry], ry - (s - 2 * rx - ry))
    return x, y


def _rect(img: np.ndarray, texel: float, c0_m: float, c1_m: float, r0_m: float, r1_m: float) -> tuple[slice, slice]:
    """Row and column slices of ``img`` for a rectangle in metres (columns, rows from the top)."""
    h, w = img.shape
    c0, c1 = max(0, int(round(c0_m / texel))), min(w, int(round(c1_m / texel)) + 1)
    r0, r1 = max(0, int(round(r0_m / texel))), min(h, int(round(r1_m / texel)) + 1)
    return slice(r0, max(r0, r1)), slice(c0, max(c0, c1))


def _wall_texture(rng: np.random.Generator, wc: dict, perimeter: float, wall_h: float, texel: float,
                  windows: list) -> np.ndarray:
    """Walls as one raster: columns along the perimeter coordinate, rows from the top (z = wall_h)."""
    w = int(math.ceil(perimeter / texel))
    h = int(math.ceil(wall_h / texel)) + 1
    tex = np.zeros((h, w), np.float32)
    s = 0.0
    while s < perimeter:
        width = float(rng.uniform(*wc["panel_width_m"]))
        c0, c1 = int(round(s / texel)), min(w, int(round((s + width) / texel)))
        tex[:, c0:c1] = rng.uniform(*wc["panel_level"])
        s += width
    mottle = smooth_noise(rng, (h, w), wc["mottle_scale_m"] / texel)
    tex += np.float32(wc["mottle_amplitude"]) * mottle
    for _ in range(int(wc["doors"])):
        dw, dh = wc["door_size_m"]
        s0 = float(rng.uniform(0, perimeter - dw))
        sl = _rect(tex, texel, s0, s0 + dw, wall_h - dh, wall_h)
        tex[sl] = wc["door_level"] + 5.0 * mottle[sl]
        hs = _rect(tex, texel, s0 + 0.75 * dw, s0 + 0.8 * dw, wall_h - 1.05, wall_h - 0.95)
        tex[hs] = 200.0
    for _ in range(int(wc["posters"])):
        pw, ph = float(rng.uniform(*wc["poster_width_m"])), float(rng.uniform(*wc["poster_height_m"]))
        bottom = float(rng.uniform(*wc["poster_bottom_m"]))
        s0 = float(rng.uniform(0, perimeter - pw))
        sl = _rect(tex, texel, s0, s0 + pw, wall_h - bottom - ph, wall_h - bottom)
        shape = tex[sl].shape
        if min(shape) < 2:
            continue
        pattern = smooth_noise(rng, shape, wc["poster_scale_m"] / texel)
        tex[sl] = rng.uniform(70, 190) + np.float32(wc["poster_contrast"]) * pattern
    tex[_rect(tex, texel, 0, perimeter, wall_h - wc["baseboard_m"], wall_h)] = wc["baseboard_level"]
    for s0, s1, z0, z1 in windows:
        tex[_rect(tex, texel, s0, s1, wall_h - z1, wall_h - z0)] = wc["window_day_level"]
    return np.clip(tex, 1.0, 254.0)


def _box_textures(rng: np.random.Generator, wc: dict, box: Box, texel: float) -> tuple[np.ndarray, np.ndarray]:
    """A box's side raster (columns along its perimeter, rows from the top) and top raster."""
    w = int(math.ceil(box.perimeter / texel))
    h = int(math.ceil(box.height / texel)) + 1
    base = float(rng.uniform(60, 200))
    side = np.full((h, w), base, np.float32)
    for _ in range(int(rng.integers(1, 4))):  # horizontal bands
        z0 = float(rng.uniform(0, box.height))
        side[_rect(side, texel, 0, box.perimeter, z0, z0 + float(rng.uniform(0.03, 0.15)))] = rng.uniform(30, 230)
    for _ in range(int(rng.integers(2, 6))):  # labels
        lw, lh = float(rng.uniform(0.1, 0.4)), float(rng.uniform(0.08, 0.3))
        s0 = float(rng.uniform(0, max(box.perimeter - lw, 1e-3)))
        z0 = float(rng.uniform(0, max(box.height - lh, 1e-3)))
        side[_rect(side, texel, s0, s0 + lw, z0, z0 + lh)] = rng.uniform(20, 240)
    side += np.float32(wc["mottle_amplitude"]) * smooth_noise(rng, side.shape, wc["mottle_scale_m"] / texel)
    th, tw = int(math.ceil(2 * box.sy / texel)) + 1, int(math.ceil(2 * box.sx / texel)) + 1
    top = base + np.float32(wc["mottle_amplitude"]) * smooth_noise(rng, (th, tw), wc["mottle_scale_m"] / texel)
    return np.clip(side, 1.0, 254.0), np.clip(top, 1.0, 254.0).astype(np.float32)


def _ceiling_texture(rng: np.random.Generator, wc: dict, grid: MapGrid, lamps: np.ndarray,
                     lamp_size: tuple[float, float]) -> np.ndarray:
    tex = np.full(grid.shape, wc["ceiling_level"], np.float32)
    tex += np.float32(0.5 * wc["mottle_amplitude"]) * smooth_noise(rng, grid.shape, wc["mottle_scale_m"] / grid.pixel_size)
    for lx, ly in lamps:
        c0, r0 = grid.world_to_pixel(lx - lamp_size[0] / 2, ly + lamp_size[1] / 2)
        c1, r1 = grid.world_to_pixel(lx + lamp_size[0] / 2, ly - lamp_size[1] / 2)
        tex[int(round(r0)) : int(round(r1)) + 1, int(round(c0)) : int(round(c1)) + 1] = wc["lamp_level"]
    return tex


def _pack(blocks: dict, pad: int, wrap: set) -> tuple[np.ndarray, dict]:
    """Shelf-pack named rasters into one atlas, each with ``pad`` texels of border.

    Borders repeat the edge (``wrap``: wrap around horizontally, for closed perimeters), so
    mip levels and bilinear sampling never mix two surfaces. Returns the atlas and
    ``name -> (col0, row0, width, height)`` of each raster's interior.
    """
    order = sorted(blocks, key=lambda k: (-blocks[k].shape[0], k))
    placed, x, y, shelf_h, width = {}, 0, 0, 0, 0
    for name in order:
        h, w = blocks[name].shape
        bw, bh = w + 2 * pad, h + 2 * pad
        if bw > _ATLAS_ROW_WIDTH:
            raise BadInput("config simulate.omni.world.texel_m", f"surface {name} is {w} texels long (max "
                                                                  f"{_ATLAS_ROW_WIDTH - 2 * pad}): use larger texels")
        if x + bw > _ATLAS_ROW_WIDTH:
            x, y, shelf_h = 0, y + shelf_h, 0
        placed[name] = (x, y)
        x += bw
        shelf_h = max(shelf_h, bh)
        width = max(width, x)
    height = y + shelf_h
    if height > _MAX_ATLAS_SIDE:
        raise BadInput("config simulate.omni.world.texel_m", "the texture atlas would be too large: use larger texels")
    atlas = np.zeros((height, width), np.float32)
    regions = {}
    for name, (x, y) in placed.items():
        b = blocks[name].astype(np.float32)
        b = np.pad(b, ((0, 0), (pad, pad)), mode="wrap" if name in wrap else "edge")
        b = np.pad(b, ((pad, pad), (0, 0)), mode="edge")
        atlas[y : y + b.shape[0], x : x + b.shape[1]] = b
        regions[name] = (x + pad, y + pad, blocks[name].shape[1], blocks[name].shape[0])
    return atlas, regions


def _place_box(rng: np.random.Generator, wc: dict, room: tuple[float, float], route_xy: np.ndarray,
               clearance: float, others: list, size: tuple[float, float, float] | None, name: str,
               tries: int = 200) -> Box | None:
    """A random box position clear of the route, the walls' inside and the other boxes (or None)."""
    for _ in range(tries):
        if size is None:
            sx, sy = (float(v) / 2 for v in rng.uniform(*wc["object_size_m"], size=2))
            hb = float(rng.uniform(*wc["object_height_m"]))
        else:
            sx, sy, hb = size
        box = Box(float(rng.uniform(0, room[0])), float(rng.uniform(0, room[1])), sx, sy,
                  float(rng.uniform(-math.pi, math.pi)), hb, name)
        cs = box.corners()
        if cs[:, 0].min() < 0.02 or cs[:, 1].min() < 0.02 or cs[:, 0].max() > room[0] - 0.02 \
                or cs[:, 1].max() > room[1] - 0.02:
            continue
        if box.distance(route_xy[:, 0], route_xy[:, 1]).min() < clearance:
            continue
        gap = wc["object_gap_m"]
        if any(math.hypot(box.cx - o.cx, box.cy - o.cy) < math.hypot(box.sx, box.sy) + math.hypot(o.sx, o.sy) + gap
               for o in others):
            continue
        return box
    return None


def _route_clearance(cfg_om: dict, opts: OmniOptions) -> float:
    """Distance (metres) objects keep from the nominal route: clearance plus the run's excursions."""
    excursion = abs(opts.offset_m) + (cfg_om["across_amplitude_m"] if opts.angle_deg else 0.0)
    return cfg_om["world"]["object_route_clearance_m"] + excursion


def generate_world(rng_tex: np.random.Generator, rng_obj: np.random.Generator, cfg: dict, room: tuple[float, float],
                   route_xy: np.ndarray, clearance: float, seed: int) -> World:
    """A fresh world over ``room`` whose objects keep ``clearance`` metres from ``route_xy`` (M, 2)."""
    om = cfg["simulate"]["omni"]
    wc = om["world"]
    texel = float(wc["texel_m"])
    if texel <= 0:
        raise BadInput("config simulate.omni.world.texel_m", "must be positive")
    wall_h = float(om["wall_height_m"])
    rx, ry = room
    perimeter = 2 * (rx + ry)
    # windows: evenly spaced along the wall y = room_y (perimeter from rx + ry to 2 rx + ry)
    n_win = int(wc["windows"])
    windows = []
    for i in range(n_win):
        centre = rx + ry + (i + 0.5) * rx / n_win
        half = min(wc["window_width_m"], rx / max(n_win, 1) * 0.8) / 2
        windows.append((centre - half, centre + half, float(wc["window_z_m"][0]), float(wc["window_z_m"][1])))
    nx, ny = wc["lamps"]
    lamps = np.array([[(i + 0.5) * rx / nx, (j + 0.5) * ry / ny] for j in range(ny) for i in range(nx)], float)
    lamp_size = (float(wc["lamp_size_m"][0]), float(wc["lamp_size_m"][1]))
    floor_grid = MapGrid.covering(0.0, 0.0, rx, ry, texel)
    floor = procedural_texture(rng_tex, floor_grid, cfg["simulate"]["floor"]["textures"], rx * ry)
    blocks = {
        "floor": floor,
        "ceiling": _ceiling_texture(rng_tex, wc, floor_grid, lamps, lamp_size),
        "walls": _wall_texture(rng_tex, wc, perimeter, wall_h, texel, windows),
    }
    objects: list[Box] = []
    for k in range(int(wc["objects"])):
        box = _place_box(rng_obj, wc, room, route_xy, clearance, objects, None, f"box{k}")
        if box is None:
            raise BadInput("config simulate.omni.world.objects",
                           f"no room for object {k + 1} of {wc['objects']} clear of the route: fewer or smaller objects")
        objects.append(box)
        blocks[f"box{k}_side"], blocks[f"box{k}_top"] = _box_textures(rng_tex, wc, box, texel)
    pad = 2 ** int(wc["mip_levels"])
    atlas, regions = _pack(blocks, pad, {"walls"} | {f"box{k}_side" for k in range(len(objects))})
    atlas = np.round(atlas * ATLAS_SCALE) / ATLAS_SCALE  # what the PNG keeps, so a --world rerun matches
    meta = {"seed": seed, "source": "procedural", "derived_from": "", "moved_fraction": 0.0, "moved_objects": []}
    return World(room, wall_h, texel, atlas.astype(np.float32), regions, objects, lamps, lamp_size, windows, meta)


def save_world(world: World, wdir: Path, route: Route, png_attributes: dict) -> None:
    """Write ``world.json``, ``atlas.png`` and the nominal ``route.csv`` into ``wdir``."""
    wdir.mkdir(parents=True, exist_ok=True)
    write_image(wdir / ATLAS_FILE, np.clip(np.rint(world.atlas * ATLAS_SCALE), 0, 65535).astype(np.uint16),
                png_attributes)
    write_json_atomic(wdir / WORLD_FILE, world.to_json())
    lines = ["s,x,y,theta"] + [f"{s!r},{x!r},{y!r},{t!r}" for s, x, y, t in
                               zip(route.s.tolist(), route.x.tolist(), route.y.tolist(), route.theta.tolist())]
    write_text_atomic(wdir / ROUTE_FILE, "\n".join(lines) + "\n")


def load_world(log: str | Path) -> tuple[World, Route]:
    """The world and nominal route of a previous omni log (``--world``); BadInput when unusable."""
    log = Path(log)
    wdir = log / WORLD_DIR
    if not log.is_dir():
        raise BadInput(log, "--world: previous log directory not found")
    for name in (WORLD_FILE, ATLAS_FILE, ROUTE_FILE):
        if not (wdir / name).is_file():
            raise BadInput(wdir / name, "--world: not found (not a log of `mosaicmap simulate omni`)")
    try:
        d = json.loads((wdir / WORLD_FILE).read_text())
        if d.get("format") != WORLD_FORMAT:
            raise ValueError(f"format is {d.get('format')!r}, expected {WORLD_FORMAT!r}")
        objects = [Box(**o) for o in d["objects"]]
        regions = {k: tuple(int(v) for v in r) for k, r in d["regions"].items()}
        meta = {k: d[k] for k in ("seed", "source", "derived_from", "moved_fraction", "moved_objects") if k in d}
        world = World((float(d["room_m"][0]), float(d["room_m"][1])), float(d["wall_height_m"]), float(d["texel_m"]),
                      np.zeros((0, 0), np.float32), regions, objects, np.asarray(d["lamps_m"], float).reshape(-1, 2),
                      tuple(d["lamp_size_m"]), [tuple(w) for w in d["windows"]], meta)
        scale = float(d.get("atlas_scale", ATLAS_SCALE))
    except (ValueError, KeyError, TypeError) as e:
        raise BadInput(wdir / WORLD_FILE, f"--world: invalid world description: {e}") from None
    raw = cv2.imread(str(wdir / ATLAS_FILE), cv2.IMREAD_UNCHANGED)  # exact uint16 (read_raw normalizes)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        raise BadInput(wdir / ATLAS_FILE, "--world: not a 16-bit grey texture atlas")
    world.atlas = raw.astype(np.float32) / np.float32(scale)
    try:
        rows = np.loadtxt(wdir / ROUTE_FILE, delimiter=",", skiprows=1, ndmin=2)
        if rows.shape[1] != 4 or len(rows) < 2:
            raise ValueError("expected columns s,x,y,theta and at least 2 rows")
    except ValueError as e:
        raise BadInput(wdir / ROUTE_FILE, f"--world: invalid route: {e}") from None
    return world, Route(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3])


# --- routes and object moves --------------------------------------------------------------


def offset_route(nominal: Route, offset_m: float, angle_deg: float, amplitude_m: float, step: float) -> Route:
    """The route actually driven: the nominal one shifted left by ``offset_m`` (metres) and,
    with a crossing angle, by a triangle wave of slope ``tan(angle)`` and ``amplitude_m``.

    Headings follow the direction of travel of the shifted path.
    """
    if offset_m == 0 and angle_deg == 0:
        return nominal
    s, th = nominal.s, nominal.theta
    d = np.full_like(s, float(offset_m))
    if angle_deg:
        k = math.tan(math.radians(abs(angle_deg)))
        period = 4.0 * amplitude_m / k
        d += math.copysign(1.0, angle_deg) * amplitude_m * (2 / np.pi) * np.arcsin(np.sin(2 * np.pi * s / period))
    pts = np.stack([nominal.x - np.sin(th) * d, nominal.y + np.cos(th) * d], axis=1)
    return from_polyline(pts, step)


def _box_slab(box: Box, x: np.ndarray, y: np.ndarray, dx: np.ndarray, dy: np.ndarray):
    """2-D ray / footprint intersection in the box frame: (t_enter, t_exit, x_face, lx, ly).

    ``x, y`` ray origins and ``dx, dy`` unit horizontal directions (world); t in metres along
    the horizontal direction; ``x_face`` is True where the ray enters through a local-x face.
    """
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    ox, oy = c * (x - box.cx) + s * (y - box.cy), -s * (x - box.cx) + c * (y - box.cy)
    ldx, ldy = c * dx + s * dy, -s * dx + c * dy
    with np.errstate(divide="ignore", invalid="ignore"):
        ix, iy = 1.0 / ldx, 1.0 / ldy
        t1, t2 = (-box.sx - ox) * ix, (box.sx - ox) * ix
        t3, t4 = (-box.sy - oy) * iy, (box.sy - oy) * iy
    txmin, txmax = np.minimum(t1, t2), np.maximum(t1, t2)
    tymin, tymax = np.minimum(t3, t4), np.maximum(t3, t4)
    t_in = np.maximum(txmin, tymin)
    t_out = np.minimum(txmax, tymax)
    return t_in, t_out, txmin > tymin, ox, oy, ldx, ldy


def horizon_hits(objects: list, poses: np.ndarray, height: float, n_azimuths: int = 360) -> np.ndarray:
    """Index of the first object seen at the horizon (elevation 0) per pose and azimuth, -1 = wall.

    ``poses`` (P, 3) world poses; azimuth ``j`` is ``2 pi j / n`` from the heading. Only boxes
    taller than the viewpoint ``height`` (metres) reach the horizon.
    """
    az = 2 * np.pi * np.arange(n_azimuths) / n_azimuths
    a = poses[:, 2:3] + az[None, :]
    dx, dy = np.cos(a), np.sin(a)
    x = np.broadcast_to(poses[:, 0:1], a.shape)
    y = np.broadcast_to(poses[:, 1:2], a.shape)
    best = np.full(a.shape, np.inf)
    ids = np.full(a.shape, -1, np.int32)
    for k, box in enumerate(objects):
        if box.height <= height:
            continue
        t_in, t_out, *_ = _box_slab(box, x, y, dx, dy)
        hit = (t_in < t_out) & (t_in > 0) & (t_in < best)
        best[hit] = t_in[hit]
        ids[hit] = k
    return ids


def move_objects(world: World, fraction: float, poses: np.ndarray, height: float, route_xy: np.ndarray,
                 clearance: float, rng: np.random.Generator, cfg_world: dict, trials: int = 30) -> tuple[list, float, list]:
    """Move boxes until about ``fraction`` of horizon azimuths see a different first object.

    Greedy: boxes in random order, each moved to the best of ``trials`` random placements
    (clear of the route and the other boxes), keeping a move only when it brings the changed
    fraction (averaged over ``poses``) closer to the target; stops within 0.02 of it.
    Returns ``(objects, achieved fraction, indices of the moved boxes)``.
    """
    before = horizon_hits(world.objects, poses, height)
    current = list(world.objects)
    achieved, moved = 0.0, []
    for k in rng.permutation(len(current)).tolist():
        if abs(achieved - fraction) <= 0.02 or achieved > fraction:
            break
        best, best_f = None, achieved
        for _ in range(trials):
            others = current[:k] + current[k + 1 :]
            b = current[k]
            cand = _place_box(rng, cfg_world, world.room, route_xy, clearance, others, (b.sx, b.sy, b.height),
                              b.texture, tries=20)
            if cand is None:
                continue
            trial = current[:k] + [cand] + current[k + 1 :]
            f = float(np.mean(horizon_hits(trial, poses, height) != before))
            if abs(f - fraction) < abs(best_f - fraction):
                best, best_f = cand, f
        if best is not None:
            current[k] = best
            achieved = best_f
            moved.append(k)
    return current, achieved, sorted(moved)


# --- rendering ---------------------------------------------------------------------------


def _pixel_angle(camera: HyperboloidCamera, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Angular size (radians) of each pixel: the mean angle to its right and lower neighbours."""
    d0 = camera.ray(np.stack([cols, rows], -1))
    d1 = camera.ray(np.stack([cols + 1.0, rows], -1))
    d2 = camera.ray(np.stack([cols, rows + 1.0], -1))
    a1 = np.arccos(np.clip((d0 * d1).sum(-1), -1, 1))
    a2 = np.arccos(np.clip((d0 * d2).sum(-1), -1, 1))
    return np.nan_to_num(0.5 * (a1 + a2), nan=float(np.nanmedian(a1)))


class OmniRenderer:
    """Renders omni frames of ``world`` by per-pixel ray casting (see the module docstring).

    Args:
        camera: the camera model (its ``ray`` gives each pixel's viewing direction).
        shape: frame shape ``(H, W)``.
        world: the room, objects and texture atlas.
        height_m: the viewpoint's actual height above the floor (metres).
        night: night illumination (lamps) instead of daylight (windows).
        cfg: ``[simulate.omni]``.
        vignetting: ``(v1, v2)`` applied (r in rim radii).
    """

    def __init__(self, camera: HyperboloidCamera, shape: tuple[int, int], world: World, height_m: float,
                 night: bool, cfg: dict, vignetting: tuple[float, float] = (0.0, 0.0)):
        self.shape = tuple(shape)
        self.world, self.night, self.h = world, night, float(height_m)
        wc, cam_cfg = cfg["world"], cfg["camera"]
        self.wc = wc
        h, w = self.shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        inside = camera.in_image_circle(np.stack([cols, rows], -1))
        r = camera.radius_px(np.stack([cols, rows], -1))
        self.hole = r <= camera.hole_radius_px if camera.hole_radius_px > 0 else np.zeros(self.shape, bool)
        idx = np.flatnonzero(inside)
        d = camera.ray(np.stack([cols.ravel()[idx], rows.ravel()[idx]], -1))
        ok = np.isfinite(d).all(-1) & (np.hypot(d[:, 0], d[:, 1]) > 1e-9)
        idx, d = idx[ok], d[ok]
        phi = np.arctan2(d[:, 1], d[:, 0])
        order = np.argsort(phi, kind="stable")
        self.idx, d, self.phi = idx[order], d[order], phi[order]
        cos_a = np.hypot(d[:, 0], d[:, 1])
        self.hx, self.hy = d[:, 0] / cos_a, d[:, 1] / cos_a
        self.cos_a, self.sin_a = cos_a, d[:, 2]
        self.tan_a = d[:, 2] / cos_a
        self.omega = _pixel_angle(camera, cols.ravel()[self.idx], rows.ravel()[self.idx])
        with np.errstate(divide="ignore"):
            self.t_vert = np.where(self.tan_a < 0, self.h / -self.tan_a,
                                   np.where(self.tan_a > 0, (world.wall_height - self.h) / self.tan_a, np.inf))
        self.gain = camera.vignetting_gain(self.shape, vignetting).ravel()[self.idx]
        self.hole_gain = camera.vignetting_gain(self.shape, vignetting)[self.hole]
        self.outside_level = np.float32(cam_cfg["outside_level"])
        self.hole_level = np.float32(cam_cfg["hole_level"])
        atlas = world.atlas.copy()
        if night:  # windows dark at night
            c0, r0, _, _ = world.regions["walls"]
            for s0, s1, z0, z1 in world.windows:
                rs, cs = _rect(atlas[r0:, c0:], world.texel, s0, s1, world.wall_height - z1, world.wall_height - z0)
                atlas[r0 + rs.start : r0 + rs.stop, c0 + cs.start : c0 + cs.stop] = wc["window_night_level"]
        self.levels = [atlas]
        for _ in range(int(wc["mip_levels"]) - 1):
            self.levels.append(cv2.pyrDown(self.levels[-1]))
        n = len(self.idx)
        self._block = 1024
        self._n_pad = -(-n // self._block) * self._block

    # per-frame pieces --------------------------------------------------------------------

    def _azimuth_range(self, lo: float, hi: float) -> list[slice]:
        """Index slices of the azimuth-sorted pixels with camera azimuth in [lo, hi] (wrapping)."""
        lo, hi = float(wrap_angle(lo)), float(wrap_angle(hi))
        if lo <= hi:
            return [slice(int(np.searchsorted(self.phi, lo)), int(np.searchsorted(self.phi, hi, "right")))]
        return [slice(int(np.searchsorted(self.phi, lo)), len(self.phi)),
                slice(0, int(np.searchsorted(self.phi, hi, "right")))]

    def trace(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ray-cast every active pixel at ``pose``: (texture value, hit x, hit y, hit z)."""
        world, texel = self.world, self.world.texel
        x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
        c, s = math.cos(th), math.sin(th)
        dx = c * self.hx - s * self.hy
        dy = s * self.hx + c * self.hy
        rx, ry = world.room
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.where(dx > 0, (rx - x) / dx, np.where(dx < 0, -x / dx, np.inf))
            ty = np.where(dy > 0, (ry - y) / dy, np.where(dy < 0, -y / dy, np.inf))
        t_wall = np.minimum(tx, ty)
        tau = np.minimum(t_wall, self.t_vert)
        sid = np.where(t_wall < self.t_vert, _WALL, np.where(self.tan_a < 0, _FLOOR, _CEILING)).astype(np.int16)
        n = len(tau)
        tc = np.empty(n)  # atlas column, row (level 0) and 3-D incidence cosine of the hit
        tr = np.empty(n)
        inc = np.empty(n)
        for k, box in enumerate(world.objects):
            ang = np.arctan2(box.corners()[:, 1] - y, box.corners()[:, 0] - x)
            centre = math.atan2(box.cy - y, box.cx - x)
            rel = wrap_angle(ang - centre)
            for sl in self._azimuth_range(centre + rel.min() - th, centre + rel.max() - th):
                if sl.stop <= sl.start:
                    continue
                t_in, t_out, x_face, ox, oy, ldx, ldy = _box_slab(box, x, y, dx[sl], dy[sl])
                tan_a = self.tan_a[sl]
                z_in = self.h + t_in * tan_a
                z_out = self.h + t_out * tan_a
                hit2d = (t_in < t_out) & (t_in > 0)
                side = hit2d & (z_in >= 0) & (z_in <= box.height)
                with np.errstate(divide="ignore", invalid="ignore"):
                    t_top = (box.height - self.h) / tan_a
                top = hit2d & ~side & (z_in > box.height) & (z_out < box.height) & (tan_a < 0)
                t_box = np.where(side, t_in, np.where(top, t_top, np.inf))
                win = t_box < tau[sl]
                if not win.any():
                    continue
                w_idx = np.flatnonzero(win) + sl.start
                tb = t_box[win]
                lx, ly = ox + tb * ldx[win], oy + tb * ldy[win]
                is_side = side[win]
                xf = x_face[win]
                # perimeter coordinate: +x face, +y face, -x face, -y face (counter-clockwise)
                per = np.select(
                    [xf & (lx > 0), ~xf & (ly > 0), xf & (lx <= 0)],
                    [box.sy + ly, 2 * box.sy + (box.sx - lx), 2 * box.sy + 2 * box.sx + (box.sy - ly)],
                    4 * box.sy + 2 * box.sx + (lx + box.sx),
                )
                zb = self.h + tb * tan_a[win]
                c0s, r0s, _, _ = world.regions[f"{box.texture}_side"]
                c0t, r0t, _, _ = world.regions[f"{box.texture}_top"]
                tc[w_idx] = np.where(is_side, c0s + per / texel, c0t + (lx + box.sx) / texel)
                tr[w_idx] = np.where(is_side, r0s + (box.height - zb) / texel, r0t + (box.sy - ly) / texel)
                ca = self.cos_a[w_idx]
                inc[w_idx] = np.where(is_side, np.where(xf, np.abs(ldx[win]), np.abs(ldy[win])) * ca,
                                      np.abs(self.sin_a[w_idx]))
                tau[w_idx] = tb
                sid[w_idx] = 3 + k
        hx, hy = x + tau * dx, y + tau * dy
        hz = self.h + tau * self.tan_a
        # walls, floor, ceiling
        wall = sid == _WALL
        per = np.select([ty > tx], [np.where(dx > 0, rx + hy, 2 * rx + ry + (ry - hy))],
                        np.where(dy < 0, hx, rx + ry + (rx - hx)))
        c0, r0, _, _ = world.regions["walls"]
        tc = np.where(wall, c0 + per / texel, tc)
        tr = np.where(wall, r0 + (world.wall_height - hz) / texel, tr)
        inc = np.where(wall, np.where(ty > tx, np.abs(dx), np.abs(dy)) * self.cos_a, inc)
        for code, name in ((_FLOOR, "floor"), (_CEILING, "ceiling")):
            m = sid == code
            c0, r0, _, _ = world.regions[name]
            tc = np.where(m, c0 + hx / texel, tc)
            tr = np.where(m, r0 + (ry - hy) / texel, tr)
            inc = np.where(m, np.abs(self.sin_a), inc)
        footprint = tau / self.cos_a * self.omega / np.sqrt(np.maximum(inc, 0.05))
        value = self._sample(tc, tr, footprint / texel)
        return value, hx, hy, hz

    def _sample(self, cols: np.ndarray, rows: np.ndarray, footprint_texels: np.ndarray) -> np.ndarray:
        """Trilinear mip sampling of the atlas at level-0 positions (bilinear per level)."""
        nl = len(self.levels)
        lev = np.clip(np.log2(np.maximum(footprint_texels, 1e-6)), 0.0, nl - 1.0)
        n = len(cols)
        shape = (self._n_pad // self._block, self._block)
        mc = np.zeros(self._n_pad, np.float32)
        mr = np.zeros(self._n_pad, np.float32)
        samples = np.empty((nl, n), np.float32)
        for i, img in enumerate(self.levels):
            f = 0.5**i  # pyrDown: level-i pixel j is centred on level-(i-1) pixel 2j
            mc[:n], mr[:n] = cols * f, rows * f
            samples[i] = cv2.remap(img, mc.reshape(shape), mr.reshape(shape), cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE).ravel()[:n]
        l0 = np.minimum(np.floor(lev).astype(np.intp), nl - 1)
        l1 = np.minimum(l0 + 1, nl - 1)
        frac = (lev - l0).astype(np.float32)
        ar = np.arange(n)
        return samples[l0, ar] * (1 - frac) + samples[l1, ar] * frac

    def shading(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Illumination factor at world points (metres): daylight from the windows or lamps."""
        wc = self.wc
        if not self.night:
            return (wc["day_ambient"] + wc["day_window_gain"]
                    * np.exp(-(self.world.room[1] - y) / wc["day_falloff_m"])).astype(np.float32)
        out = np.full(x.shape, wc["night_ambient"], np.float64)
        k = -0.5 / wc["night_lamp_sigma_m"] ** 2
        for lx, ly in self.world.lamps:
            out += wc["night_lamp_gain"] * np.exp(k * ((x - lx) ** 2 + (y - ly) ** 2))
        return out.astype(np.float32)

    def clean(self, pose: np.ndarray) -> np.ndarray:
        """The frame without sensor effects (float32 ``(H, W)``; outside the annulus: 0)."""
        value, hx, hy, _ = self.trace(pose)
        img = np.zeros(self.shape, np.float32)
        img.ravel()[self.idx] = value * self.shading(hx, hy)
        return img

    def render(self, pose: np.ndarray, gain: float, noise_sigma: float, rng: np.random.Generator) -> np.ndarray:
        """A raw 8-bit frame at ``pose``: scene x shading x vignetting x ``gain``, the image
        circle (outside level, the camera's reflection in the hole), Gaussian noise of
        ``noise_sigma`` grey levels, rounding."""
        value, hx, hy, _ = self.trace(pose)
        img = np.full(self.shape, self.outside_level, np.float32)
        img[self.hole] = self.hole_level * self.hole_gain * np.float32(gain)
        img.ravel()[self.idx] = value * self.shading(hx, hy) * self.gain * np.float32(gain)
        if noise_sigma > 0:
            img += rng.standard_normal(self.shape, dtype=np.float32) * np.float32(noise_sigma)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# --- the simulation ----------------------------------------------------------------------


def _check_clear(poses: np.ndarray, world: World, where: str) -> None:
    """Every pose keeps the vehicle's radius from the walls and the objects."""
    rx, ry = world.room
    r = BODY_RADIUS_M
    bad = (poses[:, 0] < r) | (poses[:, 0] > rx - r) | (poses[:, 1] < r) | (poses[:, 1] > ry - r)
    for b in world.objects:
        bad |= b.distance(poses[:, 0], poses[:, 1]) < r
    if bad.any():
        i = int(np.argmax(bad))
        raise BadInput(where, f"the route runs into a wall or an object (frame {i} at x={poses[i, 0]:.2f}, "
                              f"y={poses[i, 1]:.2f} m; the vehicle needs {r} m around it)")


def simulate_omni(out: str | Path, cfg: dict, given: dict, *, quiet: bool = False) -> dict:
    """Simulate one omni drive log into ``out`` (atomically). Returns a summary dict.

    Args:
        out: output log directory; must not exist or be empty.
        cfg: the effective configuration (``load_config``).
        given: command-line values (None = not given): seed, room, route, world, night,
            height_offset, move_objects, offset, angle, noise, odometry_drift, route_id.
    """
    t_start = time.perf_counter()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BadInput(out, "output already exists and is not an empty directory")
    om = cfg["simulate"]["omni"]
    opts = resolve_options(cfg, given)
    streams = dict(zip(_STREAMS, np.random.SeedSequence(opts.seed).spawn(len(_STREAMS))))

    def rng(name: str) -> np.random.Generator:
        return np.random.default_rng(streams[name])

    camera = camera_from_config(om["camera"])
    w, h = om["camera"]["frame_size"]
    motion, routes = om["motion"], om["routes"]
    spacing = float(motion["frame_spacing_m"])
    if spacing <= 0 or motion["speed_m_s"] <= 0:
        raise BadInput("config simulate.omni.motion", "frame_spacing_m and speed_m_s must be positive")
    clearance = _route_clearance(om, opts)
    if opts.world:
        world, nominal = load_world(opts.world)
        world.meta = {**world.meta, "derived_from": world.meta.get("source", ""), "source": f"world:{opts.world}",
                      "moved_fraction": 0.0, "moved_objects": []}
    else:
        lane = float(routes["lane_spacing_m"]) / max(1e-6, 1.0 - float(routes["lane_overlap"]))
        nominal = make_route(opts.route, opts.room_m, rng("route"), routes, lane)
        world = None
    actual = offset_route(nominal, opts.offset_m, opts.angle_deg, om["across_amplitude_m"], routes["dense_step_m"])
    route_xy = np.stack([nominal.x, nominal.y], 1)[:: max(1, int(0.05 / routes["dense_step_m"]))]
    if world is None:
        world = generate_world(rng("texture"), rng("objects"), cfg, opts.room_m, route_xy, clearance, opts.seed)
    s_frames = actual.samples(spacing)
    gt_poses = actual.at(s_frames)
    height = camera.height_m + opts.height_offset_m
    if opts.height_offset_m and height >= world.wall_height - 0.05:
        raise BadInput("--height-offset", f"puts the camera at {height:.2f} m, above the world's ceiling")
    if opts.move_objects > 0:
        if not world.objects:
            raise BadInput("--move-objects", "the world has no objects to move")
        sample = gt_poses[np.unique(np.linspace(0, len(gt_poses) - 1, min(len(gt_poses), 48)).round().astype(int))]
        objects, achieved, moved = move_objects(world, opts.move_objects, sample, height, route_xy,
                                                clearance, rng("move"), om["world"])
        world.objects = objects
        world.meta = {**world.meta, "moved_fraction": achieved, "moved_objects": moved}
    _check_clear(gt_poses, world, "--world" if opts.world else "config simulate.omni.routes")

    # --- times, odometry, ground truth -------------------------------------------------
    speed = float(motion["speed_m_s"])
    t0 = float(motion["start_time_s"])
    frame_t = t0 + s_frames / speed
    odo_cfg = om["odometry"]
    odo_t = odometry_times(frame_t[0], frame_t[-1], odo_cfg["rate_hz"])
    odo_gt = actual.at((odo_t - t0) * speed)
    odo = simulate_odometry(odo_gt, opts.odometry_drift, rng("odometry"), odo_cfg)
    gains = exposure_gain(frame_t - t0, rng("exposure"), om["sensor"])
    frame_streams = streams["frames"].spawn(len(s_frames))

    vig = tuple(float(v) for v in om["camera"]["vignetting"])
    renderer = OmniRenderer(camera, (h, w), world, height, opts.night, om, vig)
    png_attributes = {"png:compressionLevel": int(om["png_compression"])}
    if om["png_filter"]:
        png_attributes["png:filter"] = int(om["png_filter"])
    images = [f"{IMAGES_DIR}/{i:06d}.png" for i in range(len(s_frames))]
    workers = cfg["simulate"]["workers"] or (os.cpu_count() or 1)
    render_s = [0.0] * len(images)

    with atomic_dir(out, replace=out.exists()) as tmp:
        (tmp / IMAGES_DIR).mkdir()

        def one(i: int) -> None:
            t = time.perf_counter()
            img = renderer.render(gt_poses[i], float(gains[i]), opts.noise_sigma,
                                  np.random.default_rng(frame_streams[i]))
            render_s[i] = time.perf_counter() - t
            write_image(tmp / images[i], img, png_attributes)

        with ThreadPoolExecutor(max_workers=workers) as ex:
            for _ in progress(ex.map(one, range(len(images))), length=len(images), label="simulate omni", unit="frames",
                              quiet=quiet):
                pass
        save_world(world, tmp / WORLD_DIR, nominal, {"png:compressionLevel": 6})
        options = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(opts).items()}
        options["room_m"] = list(world.room)
        extra = {
            "simulation": {
                "generator": "mosaicmap simulate omni",
                "seed": opts.seed,
                "world": opts.world,
                "world_dir": WORLD_DIR,
                "route_length_m": actual.length,
                "nominal_route_length_m": nominal.length,
                "odometry_frame": odo_cfg["frame"],
                "rendered_height_m": height,
                "vignetting_rendered": list(vig),
                "moved_fraction": float(world.meta.get("moved_fraction", 0.0)),
                "config_sha256": config_hash(cfg["simulate"]["omni"]),
                "options": options,
            }
        }
        spec = CameraSpec(model="omni", omni=camera, vignetting=vig if om["camera"]["declare_vignetting"] else None)
        write_drive_log(tmp, spec, frame_t, images, np.column_stack([odo_t, odo]),
                        ground_truth=np.column_stack([frame_t, gt_poses]), log_id=out.name, extra=extra,
                        route_id=opts.route_id)
    return {
        "frames": len(images),
        "route_length_m": actual.length,
        "route": opts.route if not opts.world else "world",
        "route_id": opts.route_id,
        "seconds": time.perf_counter() - t_start,
        "render_s_per_frame": float(np.mean(render_s)) if render_s else 0.0,
        "moved_fraction": float(world.meta.get("moved_fraction", 0.0)),
        "out": str(out),
    }
