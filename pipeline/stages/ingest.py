"""Stage ``ingest``: drive logs -> a validated, rectified, quality-checked frames store.

For every log: validate it whole before any work (a bad log fails with exit code 2 naming
the file, line or field); interpolate odometry to the frame times on SE(2); decode each
frame (OpenImageIO), correct its flat field, rectify it to the ground plane at the map
pixel size (``[map] pixel_size_m``, one pixel size for every log), normalize its intensity,
assess its quality, and store the accepted ones. Decoding and rectifying run on a thread pool
(OpenImageIO and OpenCV release the GIL); writes stay in order on the calling thread, a whole
shard at a time.

Photometry from the data: one pass over frames sampled evenly over the log (decoded once,
hot pixels removed) gives the flat-field estimate (``[ingest.flatfield]``), the levels where
the log's raw pixels clip (:func:`pipeline.quality.exposure_levels`) and its intensity
normalization (``[ingest.photometry]``, :func:`pipeline.images.estimate_intensity_map`: a log
using a small part of its format's range, e.g. 16-bit tiles at 2 % of full scale, is
stretched to the working grey levels). Frames failing an exposure or blur gate are rejected;
frames with too little texture above the floor and their own noise are stored but flagged not
registrable (placed by their prior pose; ``placed_by_prior`` in the manifest). A gate
rejecting or flagging most of a log is warned about, naming the knob; when no frame of any
(downward) log is left registrable, ingest fails with :class:`BadInput` (exit code 2).

Aerial logs (frames.csv ``height_m`` and a camera with intrinsics; ``[ingest.ground_plane]``):
before the main pass each frame's tilt and relative height are measured from the images
(:mod:`pipeline.ground_plane`); each frame is rectified as a nadir view at its measured
height, centred on its optical axis' ground point, and its prior pose moves there from the
camera's position.

Omni logs (``[camera] model = "omni"``; :mod:`pipeline.omni_ingest`): the
"rectified" frame is the bird's-eye view of the floor annulus (``[omni]``), stored like a
downward frame; the same decode pass writes every decoded frame's horizon line to
``OUT/horizons/<k:03d>.npz`` (``k`` the log's index in the store), which the route build reads.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mapstore.grid import frame_centre, frame_pixels_to_vehicle, interpolate_trajectory, se2_compose
from pipeline.camera import Rectifier, nadir_pixel_offset, rectified_shape
from pipeline.progress import progress
from pipeline.ground_plane import GroundPlaneEstimate, GroundPlaneParams, estimate_ground_plane, frame_pairs
from pipeline.drivelog import DriveLog, read_drive_log
from pipeline.errors import BadInput
from pipeline.flatfield import calibration_flat_field, flat_field_of, vignetting_from_mean
from pipeline.framestore import QUALITY_COLUMNS, LogFramesWriter, create_store, quantize
from pipeline.images import (
    ImageLimits,
    IntensityMap,
    check_photometry_config,
    estimate_intensity_map,
    read_grey_coded,
)
from pipeline.omni_ingest import (
    BirdseyeRectifier,
    OmniFloorParams,
    horizon_sampler,
    horizons_meta,
    omni_flat_field,
    write_horizons,
)
from pipeline.parallel import opencv_threads
from pipeline.quality import (
    GATE_KNOBS,
    PRIOR_GATES,
    ExposureLevels,
    FrameAssessor,
    FrameQuality,
    clean_raw,
    exposure_levels,
)
from pipeline.stages.stage import Stage, StageParams
from pipeline.stages.workspace import Workspace

log = logging.getLogger(__name__)
# The work directory's paths relative to it, as the report names the horizon lines files.
RELATIVE = Workspace(Path())
# At most this many raw pixels (all sampled frames together) feed the log's statistics.
SAMPLE_PIXELS = 2_000_000


def load_logs(paths: list[Path], cfg: dict) -> list[DriveLog]:
    """Read and validate every log (all before any processing), including time spans."""
    follow = cfg["ingest"]["follow_symlinks"]
    logs = [read_drive_log(p, follow_symlinks=follow) for p in paths]
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
            f"frame time {float(lg.frame_t[i])!r} s is outside the odometry time span "
            f"[{float(t0)!r}, {float(t1)!r}] s "
            f"({outside.size} frames are)",
        )


@dataclass
class _Result:
    index: int
    stored: np.ndarray | None = None  # the rectified frame as the store holds it (uint16, framestore.quantize)
    quality: FrameQuality | None = None
    error: BadInput | None = None
    line: np.ndarray | None = None  # omni: the horizon line


@dataclass
class _LogSample:
    """Frames sampled evenly over a log, decoded once: what the log's statistics come from.

    Attributes:
        frames: frames decoded (undecodable or odd-sized ones are skipped: the main pass
            reports them).
        mean: per-pixel mean of the cleaned raw frames (float64, grey levels of full scale),
            when the flat field is to be estimated from it, else None.
        pos: flat raw pixel indices the values come from (the same in every frame).
        values: cleaned raw values at ``pos`` of every sampled frame (float32 ``(frames, P)``).
        hot_pixels: hot pixels removed from the sampled frames (count).
    """

    frames: int
    mean: np.ndarray | None
    pos: np.ndarray
    values: np.ndarray
    hot_pixels: int


def _sample_log(lg: DriveLog, raw_shape: tuple[int, int], count: int, q: dict, code_step: float, workers: int,
                *, want_mean: bool, raw_mask: np.ndarray | None = None,
                limits: ImageLimits | None = None) -> _LogSample:
    """Decode ``count`` frames spread evenly over the log, remove their hot pixels (as the main
    pass does) and keep a strided subsample of their pixels (within ``raw_mask`` when given)
    and, with ``want_mean``, their per-pixel mean."""
    n = len(lg.frame_images)
    idx = np.unique(np.linspace(0, n - 1, max(1, min(n, count))).round().astype(int))
    cand = np.flatnonzero(raw_mask.ravel()) if raw_mask is not None else np.arange(raw_shape[0] * raw_shape[1])
    stride = max(1, -(-cand.size * len(idx) // SAMPLE_PIXELS))
    pos = cand[stride // 2 :: stride]
    k = float(q["hot_pixel_sigmas"])

    def load(i: int):
        try:
            raw, _ = read_grey_coded(lg.image_path(i), limits=limits)
        except BadInput:
            return None  # the main pass reports it
        if raw.shape != raw_shape:
            return None
        return clean_raw(raw, k, code_step, raw_mask)

    acc = np.zeros(raw_shape, np.float64) if want_mean else None
    values, hot, frames = [], 0, 0
    with ThreadPoolExecutor(workers) as pool, opencv_threads(workers):
        for res in pool.map(load, idx):
            if res is None:
                continue
            frames += 1
            hot += res.hot_pixels
            values.append(res.pixels.ravel()[pos])
            if acc is not None:
                cv2.accumulate(res.pixels, acc)  # (float64 += float32: a quarter of numpy's time, same sums)
    vals = np.stack(values) if values else np.zeros((0, pos.size), np.float32)
    return _LogSample(frames, None if acc is None or not frames else acc / frames, pos, vals, hot)


def _flat_field(lg: DriveLog, raw_shape: tuple[int, int], cfg: dict,
                sample: _LogSample | None) -> tuple[np.ndarray | None, dict]:
    """Flat field for a log per ``[ingest.flatfield]``, and a description for the manifest.

    ``sample``: the log's sampling pass when :func:`_estimates_flat_field` (its mean frame is
    fitted)."""
    ff = cfg["ingest"]["flatfield"]
    mode = ff["mode"]
    if mode == "none":
        return None, {"source": "none"}
    flat = calibration_flat_field(lg, raw_shape, limits=ImageLimits.from_config(cfg["ingest"]))
    if flat is not None:
        src = "flat_field image" if lg.camera.flat_field else "calibration vignetting"
        return flat, {"source": src}
    if mode == "calibration":
        return None, {"source": "none (no calibration)"}
    n = len(lg.frame_images)
    if n < ff["min_frames"]:
        return None, {"source": f"none (only {n} frames, need {ff['min_frames']} to estimate)"}
    if sample is None or sample.mean is None:
        return None, {"source": "none (no frame of the sample could be decoded)"}
    v1, v2 = vignetting_from_mean(sample.mean, lg.camera)
    return flat_field_of(lg.camera, (v1, v2), raw_shape), {"source": "estimated", "frames": sample.frames,
                                                           "vignetting": [v1, v2]}


def _estimates_flat_field(lg: DriveLog, cfg: dict) -> bool:
    """Whether the log's flat field is estimated from its frames (``[ingest.flatfield]``)."""
    ff = cfg["ingest"]["flatfield"]
    mode = ff["mode"]
    if mode not in ("auto", "calibration", "none"):
        raise BadInput("config[ingest.flatfield.mode]", f"unknown mode {mode!r} (auto, calibration, none)")
    return (mode == "auto" and lg.camera.flat_field is None and lg.camera.vignetting is None
            and len(lg.frame_images) >= ff["min_frames"])


def _photometry(lg: DriveLog, sample: _LogSample, flat: np.ndarray | None, code_step: float, ing: dict
                ) -> tuple[IntensityMap, ExposureLevels, dict]:
    """The log's intensity map and exposure clip levels from its sample, and their description.

    Clip levels come from the raw values (what the exposure gates see); the intensity map
    from the flat-corrected ones (what it is applied to)."""
    raw = sample.values.ravel()
    levels = exposure_levels(raw, code_step, ing["quality"])
    vals = sample.values
    if flat is not None and vals.size:
        vals = vals / np.maximum(flat.ravel()[sample.pos], 1e-3).astype(np.float32)
    imap, info = estimate_intensity_map(vals.ravel(), ing["photometry"], code_step)
    info.update({"frames": sample.frames, "hot_pixels_in_sample": sample.hot_pixels})
    return imap, levels, info


def _ingest_log(
    lg: DriveLog, index: int, root, cfg: dict, *, workers: int, quiet: bool, ws: Workspace
) -> tuple[dict, list[dict], list[dict]]:
    """Ingest one log into ``root``'s group ``log<index>``: its summary, its rejected frames
    and its frames placed by the prior (each ``{log, frame, image, reason}``)."""
    ing = cfg["ingest"]
    pixel_size = cfg["map"]["pixel_size_m"]
    on_bad = ing["on_bad_image"]
    if on_bad not in ("fail", "skip"):
        raise BadInput("config[ingest.on_bad_image]", f"must be 'fail' or 'skip', got {on_bad!r}")
    limits = ImageLimits.from_config(ing)
    max_bad = float(ing["max_bad_fraction"])
    if not 0.0 <= max_bad <= 1.0:
        raise BadInput("config[ingest.max_bad_fraction]", f"must be within 0-1, got {max_bad:g}")
    n_frames = len(lg.frame_images)
    rejected: list[dict] = []
    unreadable: list[int] = []

    def reject(i: int, reason: str) -> None:
        rejected.append({"log": lg.log_id, "frame": i, "image": lg.frame_images[i], "reason": reason})

    def bad_image(i: int, e: BadInput) -> None:
        """An image that cannot be used: the build stops (``fail``, or past
        ``max_bad_fraction`` of the log's frames), else the frame is dropped with its reason."""
        if on_bad == "fail":
            raise e
        unreadable.append(i)
        if len(unreadable) > max_bad * n_frames:
            raise BadInput(e.where, f"{e.what} ({len(unreadable)} of the log's {n_frames} frames unusable, more than "
                                    f"[ingest] max_bad_fraction = {max_bad:g})")
        log.warning("%s frame %d skipped: %s: %s", lg.log_id, i, e.where, e.what)
        reject(i, e.what)

    # The first decodable frame fixes the raw image size (and the code step of the log's format).
    raw_shape = None
    code_step = 1.0
    for i in range(len(lg.frame_images)):
        try:
            first, code_step = read_grey_coded(lg.image_path(i), limits=limits)
            raw_shape = first.shape
            break
        except BadInput as e:
            bad_image(i, e)
    if raw_shape is None:
        raise BadInput(lg.path / "frames.csv", "no frame of the log could be decoded")

    prior = interpolate_trajectory(lg.odometry, lg.frame_t)
    # One sampling pass: flat-field estimate, clip levels, intensity normalization.
    if lg.camera.is_omni:
        flat, flat_info = omni_flat_field(lg, raw_shape, ing["flatfield"]["mode"], limits=limits)
        rect = _omni_rectifier(lg, raw_shape, pixel_size, cfg, flat)
        plane = heights = None
        sampler = horizon_sampler(lg.camera.omni, cfg["tracker"]["orp"])
        raw_mask = rect.raw_floor  # exposure, noise and photometry over the raw pixels seeing the floor annulus
        sample = _sample_log(lg, raw_shape, ing["photometry"]["sample_frames"], ing["quality"], code_step, workers,
                             want_mean=False, raw_mask=raw_mask, limits=limits)
    else:
        _check_rectified_size(lg, raw_shape, pixel_size, ing["max_rectified_pixels"])
        estimate = _estimates_flat_field(lg, cfg)
        count = ing["flatfield"]["sample_frames"] if estimate else ing["photometry"]["sample_frames"]
        sample = _sample_log(lg, raw_shape, count, ing["quality"], code_step, workers, want_mean=estimate,
                             limits=limits)
        flat, flat_info = _flat_field(lg, raw_shape, cfg, sample if estimate else None)
        plane = _estimate_ground_plane(lg, raw_shape, prior[:, :2], ing, limits, workers=workers, quiet=quiet)
        heights = lg.frame_heights if plane is None else plane.heights
        # the frame size follows the heights as measured (their scale may have moved)
        camera = lg.camera if plane is None else dataclasses.replace(lg.camera, height_m=float(np.median(heights)))
        rect = Rectifier(
            camera,
            raw_shape,
            pixel_size,
            interpolation=ing["interpolation"],
            erode_px=ing["valid_mask_erode_px"],
            flat_field=flat,
            heights=heights,
            rotations=None if plane is None else plane.rotations,
        )
        _check_rectifier(lg, rect, raw_shape)
        sampler = raw_mask = None
    imap, levels, photometry = _photometry(lg, sample, flat, code_step, ing)
    assess = FrameAssessor(rect.valid, ing["quality"], levels=levels, intensity=imap, raw_mask=raw_mask)
    if plane is not None:
        prior = _optical_axis_poses(prior, plane.rotations, plane.heights, rect.out_shape, pixel_size)
    plane_info = None if plane is None else {"mode": ing["ground_plane"]["mode"], **plane.describe()}
    attrs = {
        "log_id": lg.log_id,
        "path": str(lg.path.resolve()),
        "camera": lg.camera.to_toml_dict(),
        "raw_shape": list(raw_shape),
        "flat_field": flat_info,
        "frames_in_log": len(lg.frame_images),
        "photometry": photometry,
        "exposure": levels.describe(),
        "odometry_model": dict(lg.odometry_model),
    }
    if plane_info is not None:
        attrs["ground_plane"] = plane_info
    if lg.camera.is_omni:
        attrs["omni"] = {**rect.describe(), "route_id": lg.route_id}
    writer = LogFramesWriter(root, index, attrs, rect.valid)
    valid = rect.valid

    def process(i: int) -> _Result:
        try:
            raw, _ = read_grey_coded(lg.image_path(i), limits=limits)
        except BadInput as e:
            return _Result(i, error=e)
        if raw.shape != raw_shape:
            msg = f"image is {raw.shape[1]}x{raw.shape[0]}, the log's frames are {raw_shape[1]}x{raw_shape[0]}"
            return _Result(i, error=BadInput(lg.image_path(i), msg))
        fig = assess.clean(raw)
        if sampler is not None:
            # The horizon line from the raw frame as the vehicle samples it; the floor frame cleaned.
            corrected = rect.correct(raw)
            line = sampler.line(corrected)
            floor = imap.apply(rect(rect.correct(fig.pixels) if fig.hot_pixels else corrected), valid)
            return _Result(i, quantize(floor), assess(fig, floor), line=line)
        rectified = imap.apply(rect(fig.pixels, None if heights is None else heights[i], i), valid)
        # (quantized here, in the worker: on the main thread each numpy call of it waited
        # for the GIL behind the workers' Python, ~16 ms a 1024 px frame, and held them up)
        return _Result(i, quantize(rectified), assess(fig, rectified))

    lines: list[np.ndarray] = []
    line_frames: list[int] = []
    placed: list[dict] = []
    gates: dict[str, list[dict]] = {}  # gate -> the frames it rejected or flagged
    noises: list[float] = []
    hot_pixels = 0
    n = len(lg.frame_images)
    already = {r["frame"] for r in rejected}
    todo = [i for i in range(n) if i not in already]
    with ThreadPoolExecutor(workers) as pool, opencv_threads(workers):
        for res in progress(pool.map(process, todo), length=len(todo), label=f"ingest {lg.log_id}", unit="frames",
                            quiet=quiet):
            if res.error is not None:
                bad_image(res.index, res.error)
                continue
            if res.line is not None:  # every decoded frame has its horizon line, accepted or not
                lines.append(res.line)
                line_frames.append(res.index)
            q = res.quality
            noises.append(q.noise_sigma)
            hot_pixels += q.hot_pixels
            entry = {"log": lg.log_id, "frame": res.index, "image": lg.frame_images[res.index],
                     "reason": q.reason or q.prior_reason}
            if q.gate is not None:
                gates.setdefault(q.gate, []).append(entry)
            if q.reason is not None:
                rejected.append(entry)
                continue
            if q.prior_reason is not None:
                placed.append(entry)
            writer.append(
                res.stored,
                float(lg.frame_t[res.index]),
                prior[res.index],
                res.index,
                tuple(float(getattr(q, c)) for c in QUALITY_COLUMNS),
            )
    stored = writer.close()
    if sampler is not None:
        fr = np.asarray(line_frames, np.int32)
        write_horizons(
            ws.horizons_file(index),
            np.stack(lines) if lines else np.zeros((0, sampler.n_azimuths), np.float32),
            lg.frame_t[fr],
            fr,
            prior[fr],
            horizons_meta(lg, cfg["tracker"]["orp"]),
        )
    noise = float(np.median(noises)) if noises else None
    summary = {
        "log_id": lg.log_id,
        "frames_total": n,
        "frames_accepted": stored,
        "frames_registrable": stored - len(placed),
        "frames_placed_by_prior": len(placed),
        "frames_rejected": len(rejected),
        "frames_unusable_images": len(unreadable),
        "raw_shape": list(raw_shape),
        "rectified_shape": list(rect.out_shape),
        "ground_plane": plane_info,
        "flat_field": flat_info,
        "photometry": photometry,
        "exposure": levels.describe(),
        "noise_sigma": noise,
        "texture_threshold": None if noise is None else assess.texture_threshold(noise),
        "hot_pixels": hot_pixels,
        "gates": {g: len(v) for g, v in sorted(gates.items())},
        "warnings": _gate_warnings(lg, n, gates, ing["quality"]),
    }
    for w in summary["warnings"]:
        log.warning("%s", w)
    writer.group.attrs.update({"noise_sigma": noise, "texture_threshold": summary["texture_threshold"]})
    if sampler is not None:
        summary["omni"] = {**attrs["omni"], "horizon_lines": len(line_frames),
                           "horizons": str(RELATIVE.horizons_file(index))}
    return summary, sorted(rejected, key=lambda r: r["frame"]), sorted(placed, key=lambda r: r["frame"])


def _gate_warnings(lg: DriveLog, n: int, gates: dict[str, list[dict]], q: dict) -> list[str]:
    """One line per gate that rejected or flagged more than ``[ingest.quality] warn_fraction``
    of the log's frames: which gate, how many of how many, and the knob to change."""
    out = []
    for gate, entries in gates.items():
        if len(entries) > q["warn_fraction"] * n:
            verb = "placed by the prior (not registrable)" if gate in PRIOR_GATES else "rejected"
            out.append(f"log {lg.log_id}: {len(entries)} of {n} frames {verb} by the {gate} gate "
                       f"(first: frame {entries[0]['frame']}, {entries[0]['reason']}); "
                       f"if the data are fine, change [ingest.quality] {GATE_KNOBS.get(gate, gate)}")
    return out


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


# A rectified frame narrower than this (pixels) cannot be registered or rendered.
MIN_RECTIFIED_SIDE_PX = 8


def _estimate_ground_plane(lg: DriveLog, raw_shape: tuple[int, int], positions: np.ndarray, ing: dict,
                           limits: ImageLimits, *, workers: int, quiet: bool) -> GroundPlaneEstimate | None:
    """The log's per-frame camera tilt and height measured from its images
    (``[ingest.ground_plane]``, :mod:`pipeline.ground_plane`; ``positions`` ``(N, 2)`` the
    cameras' prior positions, metres), or None where the log is not measured."""
    params = GroundPlaneParams.from_config(ing["ground_plane"])
    cam = lg.camera
    if not params.applies(has_intrinsics=not (cam.is_omni or cam.rectified), has_heights=lg.frame_heights is not None):
        return None

    def read(i: int) -> np.ndarray | None:
        try:
            img, _ = read_grey_coded(lg.image_path(i), limits=limits)
        except BadInput:
            return None  # the main pass reports it
        return img if img.shape == raw_shape else None

    footprint_m = min(raw_shape) * max(cam.ground_pixel_size)
    pairs = frame_pairs(positions, len(lg.frame_images), params, footprint_m=footprint_m)
    with opencv_threads(workers):
        recorded = lg.frame_heights if lg.frame_heights is not None else np.full(len(lg.frame_images), cam.height_m)
        gps = params.scale_from_positions(has_heights=lg.frame_heights is not None)
        est = estimate_ground_plane(read, len(lg.frame_images), cam.camera_matrix(), cam.distortion(), params,
                                    pairs=pairs, heights=recorded, positions=positions if gps else None,
                                    min_step_m=params.min_step_fraction * footprint_m, workers=workers, quiet=quiet,
                                    label=f"ground plane {lg.log_id}")
    d = est.describe()
    log.info("ingest %s: camera tilt measured on %d of %d frames (median %s, max %s degrees), height on %d (changed by "
             "%s %% median, %s %% max; scale from the positions %s over %d pairs; %d of %d pairs matched)", lg.log_id,
             d["frames_estimated"], d["frames"], d["tilt_median_deg"], d["tilt_max_deg"], d["heights_estimated"],
             d["height_change_median_pct"], d["height_change_max_pct"], d["height_scale_from_positions"],
             d["height_scale_pairs"], d["pairs_matched"], d["pairs_tried"])
    return est


def _optical_axis_poses(prior: np.ndarray, rotations: np.ndarray, heights: np.ndarray, out_shape: tuple[int, int],
                        pixel_size: float) -> np.ndarray:
    """Prior poses ``(N, 3)`` of the camera (its position over the floor, its heading) ->
    poses of the tilt-corrected frames' centres (the optical axis' ground point,
    :func:`pipeline.camera.nadir_pixel_offset`), same heading."""
    cx, cy = frame_centre(out_shape)
    dx, dy = np.array([nadir_pixel_offset(r, float(h), pixel_size) for r, h in zip(rotations, heights)]).reshape(-1, 2).T
    xv, yv = frame_pixels_to_vehicle(cx + dx, cy + dy, out_shape, pixel_size)  # the camera, from the centre
    return se2_compose(prior, np.column_stack([-xv, -yv, np.zeros_like(xv)]))


def _check_rectifier(lg: DriveLog, rect: Rectifier, raw_shape: tuple[int, int]) -> None:
    """A calibration whose rectified frame is a sliver, or that maps no raw pixel onto the
    floor frame (wild distortion), is bad input naming drive.toml's [camera]."""
    h, w = rect.out_shape
    where = f"{lg.path / 'drive.toml'}[camera]"
    if min(h, w) < MIN_RECTIFIED_SIDE_PX:
        raise BadInput(where, f"log {lg.log_id}: rectified frames would be {w}x{h} px from {raw_shape[1]}x"
                              f"{raw_shape[0]} px images (the calibration's ground pixel is far from square)")
    if not rect.valid.any():
        raise BadInput(where, f"log {lg.log_id}: the calibration maps no pixel of the {raw_shape[1]}x{raw_shape[0]} "
                              "px images onto the floor frame (check the distortion coefficients)")


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


def _check_something_registrable(logs: list[DriveLog], summaries: list[dict]) -> None:
    """No registrable frame in any log: :class:`BadInput` with the gates' lines (nothing
    downstream could use the store). Omni logs are exempt: their horizon lines make a route
    panorama without floor frames."""
    if any(lg.camera.is_omni for lg in logs) or any(s["frames_registrable"] for s in summaries):
        return
    lines = []
    for lg, s in zip(logs, summaries):
        if s["warnings"]:
            lines.extend(s["warnings"])
        else:
            gates = ", ".join(f"{g} {k}" for g, k in s["gates"].items()) or "unreadable images"
            lines.append(f"log {lg.log_id}: none of {s['frames_total']} frames registrable ({gates})")
    where = logs[0].path if len(logs) == 1 else "ingest"
    raise BadInput(where, "no registrable frame: " + "; ".join(lines))


def run_ingest(ws: Workspace, params: StageParams) -> dict:
    """Stage entry: the build's logs into the frames store; the report's ``ingest`` section
    (and ``omni``, the omni logs' figures, when a log is omni)."""
    counts = ingest_logs(list(params.build.logs), ws, params.cfg, quiet=params.quiet)
    omni = counts.pop("omni", None)
    return {"ingest": counts, **({"omni": omni} if omni else {})}


def ingest_logs(logs: list[DriveLog], ws: Workspace, cfg: dict, *, quiet: bool = False) -> dict:
    """Ingest validated ``logs`` into the frames store (``ws.frames_store``, and the omni logs'
    horizon lines). Returns the stage's counts.

    ``ws`` is the workspace as the stage sees it while it writes (:meth:`Workspace.writing`):
    the build renames its temporary directory into place.
    """
    t_start = time.perf_counter()
    check_photometry_config(cfg["ingest"]["photometry"])
    workers = cfg["ingest"]["workers"] or os.cpu_count() or 1
    root = create_store(ws.frames_store, cfg["map"]["pixel_size_m"])
    summaries, rejected, placed = [], [], []
    for i, lg in enumerate(logs):
        s, r, pl = _ingest_log(lg, i, root, cfg, workers=workers, quiet=quiet, ws=ws)
        summaries.append(s)
        rejected.extend(r)
        placed.extend(pl)
        log.info("ingest %s: %d of %d frames accepted (%d placed by the prior)", lg.log_id, s["frames_accepted"],
                 s["frames_total"], s["frames_placed_by_prior"])
    _check_something_registrable(logs, summaries)
    root.attrs["logs"] = summaries
    seconds = time.perf_counter() - t_start
    total = sum(s["frames_total"] for s in summaries)
    out = {
        "frames_total": total,
        "frames_accepted": sum(s["frames_accepted"] for s in summaries),
        "frames_registrable": sum(s["frames_registrable"] for s in summaries),
        "frames_placed_by_prior": len(placed),
        "frames_rejected": len(rejected),
        "frames_unusable_images": sum(s["frames_unusable_images"] for s in summaries),
        "frames_per_s": total / seconds if seconds > 0 else 0.0,
        "logs": summaries,
        "rejected": rejected,
        "placed_by_prior": placed,
    }
    omni = [s["omni"] for s in summaries if "omni" in s]
    if omni:  # the omni logs' figures together (per log: logs[k].omni)
        out["omni"] = {
            "logs": len(omni),
            "horizon_lines": sum(o["horizon_lines"] for o in omni),
            "horizons_dir": str(RELATIVE.horizons_dir),
            "ground_pixel_m": max(o["ground_pixel_m"] for o in omni),
            "floor_frames": sum(s["frames_accepted"] for s in summaries if "omni" in s),
        }
    return out


# omni logs' horizon lines are sampled at ingest as the vehicle samples them ([tracker.orp])
STAGE = Stage("ingest", run_ingest, params_tables=("map", "ingest", "omni", "tracker.orp"))
