"""Stage ``ingest``: drive logs -> a validated, rectified, quality-checked frames store.

For every log: validate it whole before any work (a bad log fails with exit code 2 naming
the file, line or field); interpolate odometry to the frame times on SE(2); decode each
frame (OpenImageIO), correct its flat field, rectify it to the ground plane at the map
pixel size (``[map] pixel_size_m``, one pixel size for every log), assess its quality, and
store the accepted ones. Decoding and rectifying run on a thread pool (OpenImageIO and
OpenCV release the GIL); writes stay in order on the calling thread, a whole shard at a time.

Omni logs (``[camera] model = "omni"``, issue 7; :mod:`pipeline.omni_ingest`): the
"rectified" frame is the bird's-eye view of the floor annulus (``[omni]``), stored like a
downward frame; the same decode pass writes every decoded frame's horizon line to
``OUT/horizons/<k:03d>.npz`` (``k`` the log's index in the store), which the route build reads.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapstore.grid import interpolate_trajectory
from pipeline.camera import Rectifier, rectified_shape
from pipeline.cli_common import progress
from pipeline.drivelog import DriveLog, read_drive_log
from pipeline.errors import BadInput
from pipeline.flatfield import calibration_flat_field, estimated_flat_field
from pipeline.framestore import QUALITY_COLUMNS, STORE_NAME, LogFramesWriter, create_store
from pipeline.images import read_grey
from pipeline.omni_ingest import (
    HORIZONS_DIR,
    BirdseyeRectifier,
    OmniFloorParams,
    horizon_sampler,
    horizons_meta,
    horizons_path,
    omni_flat_field,
    write_horizons,
)
from pipeline.quality import FrameAssessor, FrameQuality

log = logging.getLogger(__name__)
# Where the horizon lines files land, relative to the work directory (the stage's directory).
HORIZONS_REL = "ingest"


def load_logs(paths: list[Path], cfg: dict) -> list[DriveLog]:
    """Read and validate every log (all before any processing), including time spans."""
    logs = [read_drive_log(p) for p in paths]
    ids = [lg.log_id for lg in logs]
    for i, lg in enumerate(logs):
        if lg.log_id in ids[:i]:
            raise BadInput(lg.path / "drive.toml", f"log id {lg.log_id!r} is given twice")
        check_time_span(lg, cfg["ingest"]["odometry_time_tolerance_s"])
    return logs


def check_time_span(lg: DriveLog, tolerance: float) -> None:
    """Every frame time must lie within the odometry time span (plus ``tolerance`` seconds)."""
    t0, t1 = lg.odometry[0, 0], lg.odometry[-1, 0]
    outside = np.flatnonzero((lg.frame_t < t0 - tolerance) | (lg.frame_t > t1 + tolerance))
    if outside.size:
        i = int(outside[0])
        raise BadInput(
            f"{lg.path / 'frames.csv'}:{i + 2}",
            f"frame time {lg.frame_t[i]!r} s is outside the odometry time span [{t0!r}, {t1!r}] s "
            f"({outside.size} frames are)",
        )


@dataclass
class _Result:
    index: int
    rectified: np.ndarray | None = None
    quality: FrameQuality | None = None
    error: BadInput | None = None
    line: np.ndarray | None = None  # omni: the horizon line


def _flat_field(lg: DriveLog, raw_shape: tuple[int, int], cfg: dict, workers: int) -> tuple[np.ndarray | None, dict]:
    """Flat field for a log per ``[ingest.flatfield]``, and a description for the manifest."""
    ff = cfg["ingest"]["flatfield"]
    mode = ff["mode"]
    if mode not in ("auto", "calibration", "none"):
        raise BadInput("config[ingest.flatfield.mode]", f"unknown mode {mode!r} (auto, calibration, none)")
    if mode == "none":
        return None, {"source": "none"}
    flat = calibration_flat_field(lg, raw_shape)
    if flat is not None:
        src = "flat_field image" if lg.camera.flat_field else "calibration vignetting"
        return flat, {"source": src}
    if mode == "calibration":
        return None, {"source": "none (no calibration)"}
    n = len(lg.frame_images)
    if n < ff["min_frames"]:
        return None, {"source": f"none (only {n} frames, need {ff['min_frames']} to estimate)"}
    idx = np.unique(np.linspace(0, n - 1, min(n, ff["sample_frames"])).round().astype(int))

    def load(i: int) -> np.ndarray | None:
        try:
            img = read_grey(lg.image_path(i))
        except BadInput:
            return None  # the main pass reports it
        return img if img.shape == raw_shape else None

    with ThreadPoolExecutor(workers) as pool:
        frames = [f for f in pool.map(load, idx) if f is not None]
    flat, (v1, v2) = estimated_flat_field(frames, lg.camera, raw_shape)
    return flat, {"source": "estimated", "frames": len(frames), "vignetting": [v1, v2]}


def _ingest_log(
    lg: DriveLog, index: int, root, cfg: dict, *, workers: int, quiet: bool, out_dir: Path
) -> tuple[dict, list[dict]]:
    ing = cfg["ingest"]
    pixel_size = cfg["map"]["pixel_size_m"]
    on_bad = ing["on_bad_image"]
    if on_bad not in ("fail", "skip"):
        raise BadInput("config[ingest.on_bad_image]", f"must be 'fail' or 'skip', got {on_bad!r}")
    rejected: list[dict] = []

    def reject(i: int, reason: str) -> None:
        rejected.append({"log": lg.log_id, "frame": i, "image": lg.frame_images[i], "reason": reason})

    # The first decodable frame fixes the raw image size.
    raw_shape = None
    for i in range(len(lg.frame_images)):
        try:
            raw_shape = read_grey(lg.image_path(i)).shape
            break
        except BadInput as e:
            if on_bad == "fail":
                raise
            reject(i, e.what)
    if raw_shape is None:
        raise BadInput(lg.path / "frames.csv", "no frame of the log could be decoded")

    if lg.camera.is_omni:
        flat, flat_info = omni_flat_field(lg, raw_shape, ing["flatfield"]["mode"])
        rect = _omni_rectifier(lg, raw_shape, pixel_size, cfg, flat)
        sampler = horizon_sampler(lg.camera.omni, cfg["tracker"]["orp"])
        raw_select = rect.raw_floor  # exposure figures over the raw pixels seeing the floor annulus
    else:
        _check_rectified_size(lg, raw_shape, pixel_size, ing["max_rectified_pixels"])
        flat, flat_info = _flat_field(lg, raw_shape, cfg, workers)
        rect = Rectifier(
            lg.camera,
            raw_shape,
            pixel_size,
            interpolation=ing["interpolation"],
            erode_px=ing["valid_mask_erode_px"],
            flat_field=flat,
            heights=lg.frame_heights,
        )
        sampler = raw_select = None
    assess = FrameAssessor(rect.valid, ing["quality"])
    prior = interpolate_trajectory(lg.odometry, lg.frame_t)
    attrs = {
        "log_id": lg.log_id,
        "path": str(lg.path.resolve()),
        "camera": lg.camera.to_toml_dict(),
        "raw_shape": list(raw_shape),
        "flat_field": flat_info,
        "frames_in_log": len(lg.frame_images),
    }
    if lg.camera.is_omni:
        attrs["omni"] = {**rect.describe(), "route_id": lg.route_id}
    writer = LogFramesWriter(root, index, attrs, rect.valid)

    def process(i: int) -> _Result:
        try:
            raw = read_grey(lg.image_path(i))
        except BadInput as e:
            return _Result(i, error=e)
        if raw.shape != raw_shape:
            msg = f"image is {raw.shape[1]}x{raw.shape[0]}, the log's frames are {raw_shape[1]}x{raw_shape[0]}"
            return _Result(i, error=BadInput(lg.image_path(i), msg))
        if sampler is not None:
            corrected = rect.correct(raw)
            rectified = rect(corrected)
            return _Result(i, rectified, assess(raw[raw_select], rectified), line=sampler.line(corrected))
        rectified = rect(raw, None if lg.frame_heights is None else lg.frame_heights[i])
        return _Result(i, rectified, assess(raw, rectified))

    lines: list[np.ndarray] = []
    line_frames: list[int] = []
    n = len(lg.frame_images)
    already = {r["frame"] for r in rejected}
    todo = [i for i in range(n) if i not in already]
    with ThreadPoolExecutor(workers) as pool:
        for res in progress(pool.map(process, todo), length=len(todo), label=f"ingest {lg.log_id}", quiet=quiet):
            if res.error is not None:
                if on_bad == "fail":
                    raise res.error
                reject(res.index, res.error.what)
                continue
            if res.line is not None:  # every decoded frame has its horizon line, accepted or not
                lines.append(res.line)
                line_frames.append(res.index)
            q = res.quality
            if q.reason is not None:
                reject(res.index, q.reason)
                continue
            writer.append(
                res.rectified,
                float(lg.frame_t[res.index]),
                prior[res.index],
                res.index,
                tuple(getattr(q, c) for c in QUALITY_COLUMNS),
            )
    stored = writer.close()
    if sampler is not None:
        fr = np.asarray(line_frames, np.int32)
        write_horizons(
            horizons_path(out_dir, index),
            np.stack(lines) if lines else np.zeros((0, sampler.n_azimuths), np.float32),
            lg.frame_t[fr],
            fr,
            prior[fr],
            horizons_meta(lg, cfg["tracker"]["orp"]),
        )
    summary = {
        "log_id": lg.log_id,
        "frames_total": n,
        "frames_accepted": stored,
        "frames_rejected": len(rejected),
        "raw_shape": list(raw_shape),
        "rectified_shape": list(rect.out_shape),
        "flat_field": flat_info,
    }
    if sampler is not None:
        summary["omni"] = {**attrs["omni"], "horizon_lines": len(line_frames),
                           "horizons": str(horizons_path(Path(HORIZONS_REL), index))}
    return summary, sorted(rejected, key=lambda r: r["frame"])


def _check_rectified_size(lg: DriveLog, raw_shape: tuple[int, int], pixel_size: float, max_pixels: int) -> None:
    """A map pixel far finer than a downward camera's ground pixel is a usage error."""
    out_shape = rectified_shape(lg.camera, raw_shape, pixel_size)
    if out_shape[0] * out_shape[1] > max_pixels:
        gx, gy = lg.camera.ground_pixel_size
        raise BadInput(
            "config[map.pixel_size_m]",
            f"{pixel_size} m is {min(gx, gy) / pixel_size:.0f}x finer than log {lg.log_id}'s ground pixel "
            f"({min(gx, gy):.4g} m): rectified frames would be {out_shape[1]}x{out_shape[0]} px "
            f"(max {max_pixels}); set [map] pixel_size_m near the camera's ground pixel",
        )


def _omni_rectifier(lg: DriveLog, raw_shape: tuple[int, int], pixel_size: float, cfg: dict,
                    flat: np.ndarray | None) -> BirdseyeRectifier:
    """The bird's-eye rectifier of an omni log, with the same size rule as downward frames."""
    ing = cfg["ingest"]
    params = OmniFloorParams.from_config(cfg["omni"])
    try:
        rect = BirdseyeRectifier(lg.camera.omni, raw_shape, pixel_size, params, interpolation=ing["interpolation"],
                                 erode_px=ing["valid_mask_erode_px"], flat_field=flat)
    except ValueError as e:
        raise BadInput(lg.path / "drive.toml[camera]", f"log {lg.log_id}: {e} (see configs/omni.toml [omni])") from None
    h, w = rect.out_shape
    g = rect.annulus.ground_pixel_m
    if h * w > ing["max_rectified_pixels"]:
        raise BadInput(
            "config[map.pixel_size_m]",
            f"{pixel_size} m is {g / pixel_size:.0f}x finer than omni log {lg.log_id}'s floor ground pixel "
            f"({g:.4g} m): bird's-eye frames would be {w}x{h} px (max {ing['max_rectified_pixels']}); "
            f"set [map] pixel_size_m near the camera's ground pixel",
        )
    if pixel_size < 0.5 * g:
        log.warning("omni log %s: map pixel %.4g m is %.1fx finer than the camera's floor ground pixel %.4g m "
                    "(bird's-eye frames %dx%d px): [map] pixel_size_m of 0.6-1x that would do (configs/omni.toml)",
                    lg.log_id, pixel_size, g / pixel_size, g, w, h)
    return rect


def run_ingest(logs: list[DriveLog], out_dir: Path, cfg: dict, *, quiet: bool = False) -> dict:
    """Ingest validated ``logs`` into ``out_dir/frames.zarr``. Returns the stage's counts.

    ``out_dir`` is the stage's temporary directory: the caller renames it into place.
    """
    t_start = time.perf_counter()
    workers = cfg["ingest"]["workers"] or os.cpu_count() or 1
    root = create_store(out_dir / STORE_NAME, cfg["map"]["pixel_size_m"])
    summaries, rejected = [], []
    for i, lg in enumerate(logs):
        s, r = _ingest_log(lg, i, root, cfg, workers=workers, quiet=quiet, out_dir=out_dir)
        summaries.append(s)
        rejected.extend(r)
        log.info("ingest %s: %d of %d frames accepted", lg.log_id, s["frames_accepted"], s["frames_total"])
    root.attrs["logs"] = summaries
    seconds = time.perf_counter() - t_start
    total = sum(s["frames_total"] for s in summaries)
    out = {
        "frames_total": total,
        "frames_accepted": sum(s["frames_accepted"] for s in summaries),
        "frames_rejected": len(rejected),
        "frames_per_s": total / seconds if seconds > 0 else 0.0,
        "logs": summaries,
        "rejected": rejected,
    }
    omni = [s["omni"] for s in summaries if "omni" in s]
    if omni:  # the omni logs' figures together (per log: logs[k].omni)
        out["omni"] = {
            "logs": len(omni),
            "horizon_lines": sum(o["horizon_lines"] for o in omni),
            "horizons_dir": f"{HORIZONS_REL}/{HORIZONS_DIR}",
            "ground_pixel_m": max(o["ground_pixel_m"] for o in omni),
            "floor_frames": sum(s["frames_accepted"] for s in summaries if "omni" in s),
        }
    return out
