"""Floor simulator: a world texture, a route, raw camera frames, odometry and ground truth.

Output (a drive log v1, :mod:`pipeline.drivelog`, plus the world for evaluation)::

    OUT/drive.toml, frames.csv, odometry.csv, ground_truth.csv   (write_drive_log)
    OUT/images/000000.png ...        raw (distorted, vignetted, noisy) grey frames
    OUT/world/texture.tif            float32 world texture, grey levels 0..255
    OUT/world/grid.json              MapGrid.to_attrs() of the texture raster
    OUT/world/world.json             area, source and provenance of the world
    OUT/world/changes.png, .json     with --changes: mask (0/255, same grid) and list
    OUT/ground_truth_height.csv      with --height-jitter: t,height_m,scale per frame

Height jitter (``--height-jitter FRACTION``): the camera height varies smoothly along the
path, unknown to the pipeline (drive.toml keeps the calibrated ``height_m``, frames.csv has
no ``height_m``): frame i is rendered from ``height_m x scale_i`` with ``log scale_i`` a sum
of random sinusoids of the path distance (wavelengths ``height_jitter_wavelength_m`` to 4x
that), zero-mean over the frames (the calibrated height is the frames' geometric mean
height) and at most ``log(1 + FRACTION)`` in magnitude. The truth goes to
``ground_truth_height.csv`` (``t`` as frames.csv, ``height_m``, ``scale`` = height /
calibrated height: what ``[optimize] pose_model = "similarity2"`` estimates per frame).

Conventions are :mod:`mapstore.grid`'s: a pose is the image centre's position on the floor
and the heading (world frame, metres, radians). Raw frames are rendered with the shared
camera model (:func:`pipeline.camera.raw_pixel_ground_offsets`): every raw pixel sees a
vehicle-frame floor point, transformed by the ground-truth pose to the world and sampled
from the texture with cubic interpolation.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from mapstore.grid import MapGrid
from pipeline.camera import raw_pixel_ground_offsets, vignetting_gain
from pipeline.progress import progress
from pipeline.config import config_hash
from pipeline.drivelog import CameraSpec, write_drive_log
from pipeline.errors import BadInput
from pipeline.fsutil import atomic_dir, write_json_atomic
from pipeline.images import write_image
from pipeline.resample import ExactSampler
from pipeline.simulate.changes import apply_changes
from pipeline.simulate.odometry import odometry_times, simulate_odometry
from pipeline.simulate.route import ROUTES, Route, make_route
from pipeline.simulate.texture import photo_texture, procedural_texture, read_float_tiff, write_float_tiff

__all__ = [
    "FloorOptions",
    "resolve_options",
    "camera_from_config",
    "FrameRenderer",
    "exposure_gain",
    "load_world",
    "simulate_floor",
    "height_jitter_scales",
]

WORLD_DIR = "world"
TEXTURE_FILE = "texture.tif"
GRID_FILE = "grid.json"
WORLD_FILE = "world.json"
CHANGES_MASK_FILE = "changes.png"
CHANGES_FILE = "changes.json"
IMAGES_DIR = "images"
HEIGHT_TRUTH_FILE = "ground_truth_height.csv"

# cv2.remap refuses sources of SHRT_MAX pixels or more per side (OpenCV limit, not a knob).
_MAX_RASTER_PX = 32767

# Independent random streams, spawned from the seed in this order (do not reorder:
# reproducibility of existing seeds depends on it).
_STREAMS = ("texture", "route", "odometry", "changes", "exposure", "frames", "height")


@dataclass(frozen=True)
class FloorOptions:
    """The effective, validated options of one simulation (units in the names)."""

    seed: int
    area_m: tuple[float, float]
    pixel_size_m: float
    frame_size: tuple[int, int]  # (width, height) pixels
    route: str
    odometry_drift: float
    noise_sigma: float
    texture: str  # "procedural" or an image path
    world: str  # previous log path, "" for a fresh world
    changes: int
    illumination: float
    height_jitter: float = 0.0  # peak relative camera height variation (0.02 = +-2 %)


_PAIR = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*[xX×]\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*$")


def parse_pair(text: str, where: str, *, integer: bool = False) -> tuple:
    """Parse ``"AxB"`` into two positive numbers; :class:`BadInput` naming ``where`` otherwise."""
    m = _PAIR.match(str(text))
    what = "WIDTHxHEIGHT in pixels" if integer else "XxY in metres"
    if not m:
        raise BadInput(where, f"expected {what} (e.g. {'320x240' if integer else '5x5'}), got {text!r}")
    a, b = float(m.group(1)), float(m.group(2))
    if integer:
        if a != int(a) or b != int(b):
            raise BadInput(where, f"expected whole pixel counts, got {text!r}")
        a, b = int(a), int(b)
    if a <= 0 or b <= 0:
        raise BadInput(where, f"both sizes must be positive, got {text!r}")
    return a, b


def resolve_options(cfg: dict, given: dict) -> FloorOptions:
    """Overlay command-line values ``given`` (None = not given) on the configuration and validate.

    Raises :class:`BadInput` naming the option (or configuration key) at fault.
    """
    sim, fl = cfg["simulate"], cfg["simulate"]["floor"]
    cam = fl["camera"]

    def pick(opt: str, value, key: str):
        """(value, where): the command-line value when given, else the config key's."""
        return (value, f"--{opt}") if value is not None else (fl[key], f"config simulate.floor.{key}")

    seed = given.get("seed")
    seed, where = (seed, "--seed") if seed is not None else (sim["seed"], "config simulate.seed")
    if not isinstance(seed, int) or seed < 0:
        raise BadInput(where, f"must be a non-negative integer, got {seed!r}")

    if given.get("area") is not None:
        area = parse_pair(given["area"], "--area")
    else:
        a = fl["area_m"]
        if not (isinstance(a, list) and len(a) == 2 and all(isinstance(v, (int, float)) and v > 0 for v in a)):
            raise BadInput("config simulate.floor.area_m", f"must be two positive numbers, got {a!r}")
        area = (float(a[0]), float(a[1]))
    if given.get("frame_size") is not None:
        frame = parse_pair(given["frame_size"], "--frame-size", integer=True)
    else:
        f = cam["frame_size"]
        if not (isinstance(f, list) and len(f) == 2 and all(isinstance(v, int) and v > 0 for v in f)):
            raise BadInput("config simulate.floor.camera.frame_size", f"must be two positive integers, got {f!r}")
        frame = (f[0], f[1])
    min_px = 8
    if min(frame) < min_px:
        raise BadInput("--frame-size", f"frames must be at least {min_px} pixels each way, got {frame[0]}x{frame[1]}")

    ps, where = pick("pixel-size", given.get("pixel_size"), "pixel_size_m")
    if not (isinstance(ps, (int, float)) and math.isfinite(ps) and ps > 0):
        raise BadInput(where, f"must be a positive number of metres, got {ps!r}")
    route, where = pick("route", given.get("route"), "route")
    if route not in ROUTES:
        raise BadInput(where, f"unknown route {route!r} (known: {', '.join(ROUTES)})")
    drift, where = (given["odometry_drift"], "--odometry-drift") if given.get("odometry_drift") is not None else (
        fl["odometry"]["drift"], "config simulate.floor.odometry.drift")
    if not (math.isfinite(drift) and 0 <= drift < 1):
        raise BadInput(where, f"must be in [0, 1), got {drift!r}")
    noise, where = (given["noise"], "--noise") if given.get("noise") is not None else (
        fl["sensor"]["noise_sigma"], "config simulate.floor.sensor.noise_sigma")
    if not (math.isfinite(noise) and noise >= 0):
        raise BadInput(where, f"noise sigma must be >= 0 grey levels, got {noise!r}")
    texture, where = pick("texture", given.get("texture"), "texture")
    if texture != "procedural":
        p = Path(texture)
        if not p.is_file():
            raise BadInput(texture, f"texture image not found ({where}; use 'procedural' or an image file)")
    changes, where = pick("changes", given.get("changes"), "changes")
    if not isinstance(changes, int) or changes < 0:
        raise BadInput(where, f"must be a non-negative integer, got {changes!r}")
    illum, where = pick("illumination", given.get("illumination"), "illumination")
    if not (math.isfinite(illum) and illum > 0):
        raise BadInput(where, f"must be a positive factor, got {illum!r}")
    jitter, where = pick("height-jitter", given.get("height_jitter"), "height_jitter")
    if not (isinstance(jitter, (int, float)) and math.isfinite(jitter) and 0 <= jitter < 0.5):
        raise BadInput(where, f"must be a fraction in [0, 0.5), got {jitter!r}")
    world = given.get("world")
    world = "" if world is None else str(world)
    if world and given.get("texture") is not None:
        raise BadInput("--texture", "cannot be combined with --world (the world brings its texture)")
    if fl["image_bits"] not in (8, 16):
        raise BadInput("config simulate.floor.image_bits", f"must be 8 or 16, got {fl['image_bits']!r}")
    return FloorOptions(
        seed=seed,
        area_m=(float(area[0]), float(area[1])),
        pixel_size_m=float(ps),
        frame_size=(int(frame[0]), int(frame[1])),
        route=route,
        odometry_drift=float(drift),
        noise_sigma=float(noise),
        texture=str(texture),
        world=world,
        changes=int(changes),
        illumination=float(illum),
        height_jitter=float(jitter),
    )


def camera_from_config(cam: dict, frame_size: tuple[int, int], pixel_size: float) -> CameraSpec:
    """The simulated camera: ``fx = fy = height_m / pixel_size`` (ground pixel = map pixel).

    ``cam`` is ``[simulate.floor.camera]``; the principal point is the image centre plus
    ``principal_offset_px``.
    """
    w, h = frame_size
    f = cam["height_m"] / pixel_size
    dx, dy = cam["principal_offset_px"]
    vig = tuple(float(v) for v in cam["vignetting"])
    return CameraSpec(
        model="downward",
        fx=f,
        fy=f,
        cx=(w - 1) / 2.0 + dx,
        cy=(h - 1) / 2.0 + dy,
        height_m=float(cam["height_m"]),
        k1=float(cam["k1"]),
        k2=float(cam["k2"]),
        p1=float(cam["p1"]),
        p2=float(cam["p2"]),
        vignetting=vig if cam["declare_vignetting"] else None,
    )


def exposure_gain(t: np.ndarray, rng: np.random.Generator, sensor: dict) -> np.ndarray:
    """Slow smooth exposure gain ``1 + amp x mean_i sin(2 pi t / P_i + phi_i)`` (within 1 +- amp)."""
    amp = sensor["exposure_drift"]
    k = max(1, int(sensor["exposure_drift_components"]))
    periods = rng.uniform(*sensor["exposure_drift_period_s"], size=k)
    phases = rng.uniform(0, 2 * np.pi, size=k)
    t = np.asarray(t, float)
    waves = np.sin(2 * np.pi * t[:, None] / periods[None, :] + phases[None, :]).mean(axis=1)
    return 1.0 + amp * waves


class FrameRenderer:
    """Renders raw frames of a downward camera from a world texture.

    The vehicle-frame floor offsets of every raw pixel are computed once (shared camera
    model); each pose only rotates and translates them into texture pixel coordinates and
    samples the texture bicubically at those exact positions
    (:class:`pipeline.resample.ExactSampler`: OpenCV's own 1/32-pixel rounding would shift
    whole frames by up to 1/64 px against their ground truth).

    Args:
        camera: the camera (intrinsics, distortion; vignetting applied in :meth:`render`).
        shape: raw frame shape ``(H, W)``.
        texture: float32 world texture (grey levels).
        grid: the texture's raster geometry.
        vignetting: ``(v1, v2)`` actually applied (whether declared or not).
        offsets: ``raw_pixel_ground_offsets(camera, shape)`` when already computed.
    """

    def __init__(self, camera: CameraSpec, shape: tuple[int, int], texture: np.ndarray, grid: MapGrid,
                 vignetting: tuple[float, float] = (0.0, 0.0),
                 offsets: tuple[np.ndarray, np.ndarray] | None = None):
        self.shape = tuple(shape)
        self.texture = np.ascontiguousarray(texture, np.float32)
        self.sampler = ExactSampler(self.texture, border=cv2.BORDER_REFLECT)
        self.grid = grid
        xv, yv = offsets if offsets is not None else raw_pixel_ground_offsets(camera, self.shape)
        # offsets in texture pixels
        self.ox = xv / grid.pixel_size
        self.oy = yv / grid.pixel_size
        cam_v = CameraSpec(**{**asdict(camera), "vignetting": tuple(vignetting)})
        self.gain = vignetting_gain(cam_v, self.shape)

    def maps(self, pose: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Texture pixel coordinates (col, row) seen by each raw pixel at ``pose`` (float64),
        the camera at ``scale`` x its height (ground offsets scale with the height)."""
        gc, gr = self.grid.world_to_pixel(pose[0], pose[1])
        c, s = math.cos(pose[2]), math.sin(pose[2])
        if scale != 1.0:
            c, s = c * scale, s * scale
        # world = pose ⊕ (xv, yv); grid column along +x, row along -y
        return gc + (c * self.ox - s * self.oy), gr - (s * self.ox + c * self.oy)

    def clean(self, pose: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """The floor as seen at ``pose`` (camera at ``scale`` x its height): texture
        resampled, no sensor effects (float32)."""
        return self.sampler(*self.maps(pose, scale))

    def render(self, sub_poses: np.ndarray, gain: float, noise_sigma: float, rng: np.random.Generator,
               bits: int = 8, scale: float = 1.0) -> np.ndarray:
        """A raw frame: mean over motion-blur ``sub_poses`` (n, 3), vignetting, gain, noise, quantisation.

        ``gain`` is the product of exposure drift and illumination; ``noise_sigma`` is in 8-bit
        grey levels; ``scale``: the camera's height over its nominal height. Returns uint8
        (``bits`` 8) or uint16 (16, grey levels x 257).
        """
        img = self.clean(sub_poses[0], scale)
        for p in sub_poses[1:]:
            img += self.clean(p, scale)
        img *= self.gain * np.float32(gain / len(sub_poses))
        if noise_sigma > 0:
            img += rng.standard_normal(self.shape, dtype=np.float32) * np.float32(noise_sigma)
        if bits == 16:
            return np.clip(np.rint(img * np.float32(257.0)), 0, 65535).astype(np.uint16)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def load_world(log: str | Path) -> tuple[np.ndarray, MapGrid, dict]:
    """The world of a previous simulated log: ``(texture, grid, world_meta)``.

    Raises :class:`BadInput` when ``log/world`` is missing or incomplete.
    """
    wdir = Path(log) / WORLD_DIR
    if not Path(log).is_dir():
        raise BadInput(log, "--world: previous log directory not found")
    for name in (TEXTURE_FILE, GRID_FILE):
        if not (wdir / name).is_file():
            raise BadInput(wdir / name, "--world: not found (the log has no simulated world)")
    try:
        grid = MapGrid.from_attrs(json.loads((wdir / GRID_FILE).read_text()))
    except (ValueError, KeyError, TypeError) as e:
        raise BadInput(wdir / GRID_FILE, f"--world: invalid grid description: {e}") from None
    meta = {}
    if (wdir / WORLD_FILE).is_file():
        try:
            meta = json.loads((wdir / WORLD_FILE).read_text())
        except ValueError as e:
            raise BadInput(wdir / WORLD_FILE, f"--world: not valid JSON: {e}") from None
    tex = read_float_tiff(wdir / TEXTURE_FILE, grid.shape)
    if tex.shape != grid.shape:
        raise BadInput(wdir / TEXTURE_FILE, f"--world: texture is {tex.shape}, grid.json says {grid.shape}")
    return tex, grid, meta


def height_jitter_scales(s: np.ndarray, fraction: float, wavelength_m: float,
                         rng: np.random.Generator, waves: int = 4) -> np.ndarray:
    """Camera height / calibrated height at path distances ``s`` (metres): ``exp(e(s))`` with
    ``e`` a sum of ``waves`` sinusoids of random wavelengths in ``[wavelength_m, 4
    wavelength_m]``, amplitudes and phases, made zero-mean over ``s`` and scaled to a peak
    ``|e| = log(1 + fraction)``. All ones when ``fraction`` is 0."""
    s = np.asarray(s, float)
    if fraction <= 0 or len(s) == 0:
        return np.ones(len(s))
    lam = wavelength_m * (1.0 + 3.0 * rng.random(waves))
    amp = rng.uniform(0.5, 1.0, waves)
    phase = rng.uniform(0.0, 2.0 * np.pi, waves)
    e = (amp[None, :] * np.sin(2.0 * np.pi * s[:, None] / lam[None, :] + phase[None, :])).sum(axis=1)
    e -= e.mean()
    peak = float(np.abs(e).max())
    if peak <= 0:
        return np.ones(len(s))
    return np.exp(e * (math.log1p(fraction) / peak))


def _blur_offsets(motion: dict, pixel_size: float) -> np.ndarray:
    """Arc-length offsets (metres) of the motion-blur sub-poses around a frame's pose."""
    length = motion["speed_m_s"] * motion["exposure_s"]
    blur_px = length / pixel_size
    if blur_px <= 0:
        return np.zeros(1)
    n = int(math.ceil(blur_px / motion["blur_step_px"])) + 1
    return (np.arange(n) / (n - 1) - 0.5) * length if n > 1 else np.zeros(1)


def _check_coverage(poses: np.ndarray, reach: float, grid: MapGrid, where: str) -> None:
    """Every floor point any frame sees must be inside the texture (with cubic support)."""
    xmin, ymin, xmax, ymax = grid.bounds
    pad = 2.5 * grid.pixel_size
    bad = (
        (poses[:, 0] - reach < xmin + pad)
        | (poses[:, 0] + reach > xmax - pad)
        | (poses[:, 1] - reach < ymin + pad)
        | (poses[:, 1] + reach > ymax - pad)
    )
    if bad.any():
        i = int(np.argmax(bad))
        raise BadInput(
            where,
            f"the route leaves the world texture (frame {i} at x={poses[i, 0]:.2f}, y={poses[i, 1]:.2f} m sees "
            f"{reach:.2f} m around it; the texture covers x {xmin:.2f}..{xmax:.2f}, y {ymin:.2f}..{ymax:.2f} m)",
        )


def simulate_floor(out: str | Path, cfg: dict, given: dict, *, quiet: bool = False) -> dict:
    """Simulate one floor drive log into ``out`` (atomically). Returns a summary dict.

    Args:
        out: output log directory; must not exist or be empty.
        cfg: the effective configuration (``load_config``).
        given: command-line values (None = not given): seed, area, pixel_size, frame_size,
            route, odometry_drift, noise, texture, world, changes, illumination.
    """
    t_start = time.perf_counter()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BadInput(out, "output already exists and is not an empty directory")
    fl = cfg["simulate"]["floor"]
    tex_cfg = fl["textures"]
    motion = fl["motion"]
    opts = resolve_options(cfg, given)
    streams = dict(zip(_STREAMS, np.random.SeedSequence(opts.seed).spawn(len(_STREAMS))))

    def rng(name: str) -> np.random.Generator:
        return np.random.default_rng(streams[name])

    # --- the world ---------------------------------------------------------------------
    area = opts.area_m
    pixel_size = opts.pixel_size_m
    world_meta: dict = {}
    if opts.world:
        texture, grid, world_meta = load_world(opts.world)
        if given.get("pixel_size") is not None and not math.isclose(given["pixel_size"], grid.pixel_size,
                                                                    rel_tol=1e-9):
            raise BadInput("--pixel-size", f"differs from the world's pixel size {grid.pixel_size} m ({opts.world})")
        pixel_size = grid.pixel_size
        if given.get("area") is None and "area_m" in world_meta:
            area = (float(world_meta["area_m"][0]), float(world_meta["area_m"][1]))
    w, h = opts.frame_size
    camera = camera_from_config(fl["camera"], opts.frame_size, pixel_size)
    blur_ds = _blur_offsets(motion, pixel_size)
    # the route first (cheap), so a route that does not fit a reused world fails fast
    footprint_h = h * camera.ground_pixel_size[1]
    route: Route = make_route(opts.route, area, rng("route"), fl["routes"], footprint_h)
    s_frames = route.samples(motion["frame_spacing_m"])
    gt_poses = route.at(s_frames)
    offsets_x, offsets_y = raw_pixel_ground_offsets(camera, (h, w))
    reach = float(np.hypot(offsets_x, offsets_y).max()) * (1.0 + opts.height_jitter) + float(np.abs(blur_ds).max())
    if opts.world:
        _check_coverage(gt_poses, reach, grid, f"--world {opts.world}")
    else:
        m = reach + fl["world_margin_m"]
        grid = MapGrid.covering(-m, -m, area[0] + m, area[1] + m, pixel_size)
        if max(grid.shape) >= _MAX_RASTER_PX:
            raise BadInput("--area", f"the world raster would be {grid.width}x{grid.height} pixels; cv2.remap "
                                     f"takes at most {_MAX_RASTER_PX - 1} per side (use a smaller area or "
                                     "a larger pixel size)")
        raster_m2 = grid.width * grid.height * pixel_size**2
        if opts.texture == "procedural":
            texture = procedural_texture(rng("texture"), grid, tex_cfg, raster_m2)
        else:
            texture = photo_texture(opts.texture, grid, tex_cfg)
    base_texture = texture
    change_list: list[dict] = []
    mask = None
    if opts.changes:
        texture, mask, change_list = apply_changes(
            base_texture, grid, area, opts.changes, rng("changes"), fl["change_kinds"], tex_cfg["band_limit_sigma_px"]
        )

    # --- times, odometry, ground truth -------------------------------------------------
    speed = motion["speed_m_s"]
    t0 = motion["start_time_s"]
    frame_t = t0 + s_frames / speed
    odo_cfg = fl["odometry"]
    odo_t = odometry_times(frame_t[0], frame_t[-1], odo_cfg["rate_hz"])
    odo_gt = route.at((odo_t - t0) * speed)
    odo = simulate_odometry(odo_gt, opts.odometry_drift, rng("odometry"), odo_cfg)
    sensor = fl["sensor"]
    gains = exposure_gain(frame_t - t0, rng("exposure"), sensor) * opts.illumination
    frame_streams = streams["frames"].spawn(len(s_frames))
    heights = height_jitter_scales(s_frames, opts.height_jitter, float(fl["height_jitter_wavelength_m"]), rng("height"))

    renderer = FrameRenderer(camera, (h, w), texture, grid, tuple(fl["camera"]["vignetting"]),
                             offsets=(offsets_x, offsets_y))
    bits = fl["image_bits"]
    png_attributes = {"png:compressionLevel": int(fl["png_compression"])}
    if fl["png_filter"]:
        png_attributes["png:filter"] = int(fl["png_filter"])
    images = [f"{IMAGES_DIR}/{i:06d}.png" for i in range(len(s_frames))]
    workers = cfg["simulate"]["workers"] or (os.cpu_count() or 1)

    with atomic_dir(out, replace=out.exists()) as tmp:
        (tmp / IMAGES_DIR).mkdir()

        def one(i: int) -> None:
            sub = route.at(s_frames[i] + blur_ds)
            img = renderer.render(sub, float(gains[i]), opts.noise_sigma, np.random.default_rng(frame_streams[i]), bits,
                                  float(heights[i]))
            write_image(tmp / images[i], img, png_attributes)

        with ThreadPoolExecutor(max_workers=workers) as ex:
            for _ in progress(ex.map(one, range(len(images))), length=len(images), label="simulate floor", unit="frames",
                              quiet=quiet):
                pass

        wdir = tmp / WORLD_DIR
        wdir.mkdir()
        write_float_tiff(wdir / TEXTURE_FILE, texture)
        write_json_atomic(wdir / GRID_FILE, grid.to_attrs())
        source = f"world:{opts.world}" if opts.world else (
            "procedural" if opts.texture == "procedural" else f"photo:{opts.texture}")
        write_json_atomic(
            wdir / WORLD_FILE,
            {
                "area_m": list(area),
                "source": source,
                "derived_from": world_meta.get("source", "") if opts.world else "",
                "seed": opts.seed,
                "changes": len(change_list),
                "texture": TEXTURE_FILE,
                "grid": GRID_FILE,
            },
        )
        if mask is not None:
            write_image(wdir / CHANGES_MASK_FILE, mask, png_attributes)
            write_json_atomic(wdir / CHANGES_FILE, change_list)

        options = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(opts).items()}
        options["area_m"] = list(area)
        options["pixel_size_m"] = pixel_size
        extra = {
            "simulation": {
                "generator": "mosaicmap simulate floor",
                "seed": opts.seed,
                "world": opts.world,
                "world_dir": WORLD_DIR,
                "route_length_m": route.length,
                "odometry_frame": odo_cfg["frame"],
                "vignetting_rendered": list(fl["camera"]["vignetting"]),
                "config_sha256": config_hash(cfg["simulate"]),
                "options": options,
            }
        }
        gt = np.column_stack([frame_t, gt_poses])
        if opts.height_jitter > 0:
            h0 = float(fl["camera"]["height_m"])
            rows = [f"{t!r},{h0 * k!r},{k!r}" for t, k in zip(frame_t.tolist(), heights.tolist())]
            (tmp / HEIGHT_TRUTH_FILE).write_text("t,height_m,scale\n" + "\n".join(rows) + "\n")
        write_drive_log(
            tmp,
            camera,
            frame_t,
            images,
            np.column_stack([odo_t, odo]),
            ground_truth=gt,
            log_id=out.name,
            extra=extra,
        )
    seconds = time.perf_counter() - t_start
    return {
        "frames": len(images),
        "route_length_m": route.length,
        "route": opts.route,
        "seconds": seconds,
        "out": str(out),
        "changes": len(change_list),
    }
