"""``mosaicmap import-geotagged``: a folder of geotagged aerial JPEGs -> drive log v1.

For nadir(-ish) frames from a drone or aircraft whose JPEGs carry EXIF GPS and, ideally,
the autopilot's XMP record (senseFly namespace: ``sensefly:Height`` above ground,
``sensefly:Heading``, ``sensefly:PitchAngle``, ``sensefly:RollAngle``, ``sensefly:UTCTime``).
All metadata is read with OpenImageIO, which presents EXIF as ``Exif:*`` / ``GPS:*`` and XMP
as ``<namespace prefix>:<name>`` attributes of the image spec.

Frames and time
    Every ``*.jpg`` / ``*.jpeg`` of IMAGE_DIR (not recursive). Times come from one source
    for the whole folder, the first that every frame has: ``Exif:DateTimeOriginal`` (plus
    ``Exif:SubsecTimeOriginal``; camera clock), ``sensefly:UTCTime`` (autopilot clock),
    ``GPS:DateStamp`` + ``GPS:TimeStamp``; when none is complete, file-name order at 1 s
    steps. Frames are sorted by (time, file name); frames sharing a time stamp (several
    shots within one whole second) keep file-name order and are spread evenly over the
    stamp's resolution (``t + k / n`` seconds for the k-th of n), so that times are strictly
    increasing as drive log v1 requires; their number is reported. ``t`` is seconds since
    the first frame (its absolute stamp is ``[source] time_origin``).

Positions (odometry.csv)
    ``GPS:Latitude`` / ``GPS:Longitude`` (degrees, minutes, seconds with ``*Ref`` N/S, E/W)
    projected to a local east/north frame around the first frame: ``x`` east, ``y`` north in
    metres, with WGS84's radii of curvature at the origin (equirectangular local tangent
    plane; over a few kilometres its error is far below GPS noise). The origin is
    ``[source] origin_latitude/origin_longitude``. (The EXIF rationals are used rather than
    ``sensefly:Latitude``, which OpenImageIO returns as a 32-bit float, ~0.1 m coarse.)

Heading (odometry theta)
    The source yaw is a compass heading (degrees clockwise from north), taken from
    ``sensefly:Heading``, else ``GPS:ImgDirection``, else ``GPS:Track`` (direction of
    travel), the first a frame has (a frame with none is bad input). The camera is mounted
    with the image *top* towards the aircraft's nose, so the image's column axis (the
    vehicle +x of :mod:`mapstore.grid`) points to the right wing, at compass ``yaw + 90``
    degrees, i.e. counter-clockwise from east ``90 - (yaw + 90) = -yaw``:
    ``theta = -yaw`` (:func:`theta_from_heading`). Verified on the Seneca flight: for 86
    consecutive pairs with heading change < 30 degrees, SIFT matches of frames downscaled
    to 600 px and a RANSAC similarity give the image-space motion; rotated by
    ``theta = -yaw`` it points along the GPS displacement (median residual 3 degrees, 73 of
    86 pairs within 30 degrees; roll and pitch up to 18 degrees scatter single pairs, while
    ``pi/2 - yaw`` or ``pi - yaw`` would be off by 90 or 180). The image rotation between
    the frames correlates with ``-dyaw`` (r = -0.78), so the image is not mirrored.
    ``tests/test_importers.py`` repeats the check on six pairs.

Camera (drive.toml)
    ``model = "downward"`` with ``fx = fy = focal_mm / sensor_width_mm * width_px``, ``cx, cy``
    the image centre (:func:`mapstore.grid.frame_centre`), no distortion (unknown), and
    ``height_m`` the *median* height above ground. ``focal_mm``: ``--focal-mm``, else
    ``Exif:FocalLength``. ``sensor_width_mm``: ``--sensor-width-mm``, else from
    ``Exif:PixelXDimension / Exif:FocalPlaneXResolution`` (with its resolution unit).
    Height per frame: ``sensefly:Height``, else ``--height-m``; with neither, bad input
    naming the file and field.

Extension files and columns (optional; drive log v1 allows them)
    ``frames.csv`` has an extra column ``height_m`` (the frame's own height above ground:
    it varies by about +-10 % over a flight; the build currently uses the median in
    drive.toml). ``attitude.csv`` (``t,roll,pitch,yaw``, radians, as the autopilot gives
    them: yaw clockwise from north, ``nan`` where absent) is written when any frame has
    roll or pitch, for later tilt correction.

Images
    Copied byte for byte (no recompression) as ``images/<file name>``. All frames of a log
    must have one size: the most common size wins; a frame of another size with the same
    aspect ratio (within 1 %) is resized to it, a frame of another aspect ratio is dropped
    with the reason (both listed in the report and in ``[source]``). With ``--max-width PX``
    wider frames are downscaled. Resized frames are written as lossless PNG
    (``images/<stem>.png``) to avoid a second JPEG generation.

Report keys (``--report FILE``): ``image_dir``, ``out``, ``frames``, ``frames_found``,
``frames_dropped`` (list of ``{image, reason}``), ``frames_resized``, ``width``, ``height``,
``time_source``, ``time_ties_spread``, ``yaw_sources`` (source -> count),
``height_sources`` (source -> count), ``focal_mm``, ``focal_source``, ``sensor_width_mm``,
``sensor_width_source``, ``fx``, ``height_m`` (median), ``height_min_m``, ``height_max_m``,
``ground_pixel_size_m`` (median height / fx), ``origin_latitude``, ``origin_longitude``,
``extent_m`` ([east span, north span]), ``path_length_m``, ``seconds``.
"""

from __future__ import annotations

import logging
import math
import shutil
import time
from collections import Counter
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import click
import numpy as np
import OpenImageIO as oiio

from mapstore.grid import frame_centre, wrap_angle
from pipeline.cli_common import config_option, progress, quiet_option, report_option, setup, write_report
from pipeline.drivelog import CameraSpec, read_drive_log, write_drive_log
from pipeline.errors import BadInput, JobFailed
from pipeline.fsutil import atomic_dir, write_text_atomic
from pipeline.import_tiles import check_out_dir

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg")
ATTITUDE_FILE = "attitude.csv"

# WGS84 ellipsoid.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

# Frames whose aspect ratio differs from the log's by less than this are resized to the
# log's size; others are dropped.
ASPECT_TOLERANCE = 0.01

# EXIF FocalPlaneResolutionUnit -> millimetres per unit (1 = none, taken as inch by EXIF).
_RES_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}

# Heading sources, in order of preference (all compass degrees, clockwise from north).
YAW_FIELDS = ("sensefly:Heading", "GPS:ImgDirection", "GPS:Track")
HEIGHT_FIELD = "sensefly:Height"
ROLL_FIELD = "sensefly:RollAngle"
PITCH_FIELD = "sensefly:PitchAngle"
TIME_SOURCES = ("Exif:DateTimeOriginal", "sensefly:UTCTime", "GPS:DateStamp+GPS:TimeStamp")


# --- pure helpers ------------------------------------------------------------------------


def dms_to_degrees(dms: object, ref: str | None, positive: str, negative: str) -> float:
    """Degrees of an EXIF (degrees, minutes, seconds) triple with its N/S or E/W reference.

    Raises:
        ValueError: not three finite numbers, or an unknown reference letter.
    """
    vals = tuple(dms) if isinstance(dms, (tuple, list)) else (dms,)
    if len(vals) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
        raise ValueError(f"expected (degrees, minutes, seconds), got {dms!r}")
    deg = abs(vals[0]) + vals[1] / 60.0 + vals[2] / 3600.0
    r = (ref or positive).strip().upper()[:1]
    if r not in (positive, negative):
        raise ValueError(f"reference {ref!r} is neither {positive} nor {negative}")
    return -deg if r == negative else deg


def local_east_north(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> tuple[np.ndarray, np.ndarray]:
    """Latitude/longitude (degrees) -> east, north metres around ``(lat0, lon0)``.

    Equirectangular local tangent plane with WGS84's meridional and prime-vertical radii of
    curvature at ``lat0``.
    """
    phi0 = math.radians(lat0)
    w = 1.0 - WGS84_E2 * math.sin(phi0) ** 2
    r_north = WGS84_A * (1.0 - WGS84_E2) / w**1.5
    r_east = WGS84_A / math.sqrt(w)
    dlon = (np.asarray(lon, float) - lon0 + 180.0) % 360.0 - 180.0
    x = np.radians(dlon) * r_east * math.cos(phi0)
    y = np.radians(np.asarray(lat, float) - lat0) * r_north
    return x, y


def theta_from_heading(yaw_deg: np.ndarray | float) -> np.ndarray | float:
    """Pose heading theta (radians, CCW from +x = east) of a frame from its compass yaw (degrees CW from north).

    The image top points to the nose, so the image column axis (vehicle +x) is at compass
    ``yaw + 90``: ``theta = 90 - (yaw + 90) = -yaw``.
    """
    return wrap_angle(-np.radians(yaw_deg))


def _parse_exif_datetime(text: str, subsec: str | None) -> tuple[float, float]:
    """Seconds (naive clock, since 1970) and resolution of an EXIF ``YYYY:MM:DD HH:MM:SS``."""
    dt = datetime.strptime(text.strip(), "%Y:%m:%d %H:%M:%S")
    s = (dt - datetime(1970, 1, 1)).total_seconds()
    digits = "".join(c for c in (subsec or "") if c.isdigit())
    if digits:
        return s + int(digits) / 10 ** len(digits), 10.0 ** -len(digits)
    return s, 1.0


def _parse_iso(text: str) -> tuple[float, float]:
    dt = datetime.fromisoformat(text.strip().replace("Z", "+00:00")).replace(tzinfo=None)
    s = (dt - datetime(1970, 1, 1)).total_seconds()
    return s, (1.0 if dt.microsecond == 0 else 1e-6)


def _parse_gps_time(date: str, hms: object) -> tuple[float, float]:
    dt = datetime.strptime(date.strip(), "%Y:%m:%d")
    h, m, s = (float(v) for v in hms)
    secs = (dt - datetime(1970, 1, 1)).total_seconds() + 3600 * h + 60 * m + s
    return secs, (1.0 if float(s).is_integer() else 1e-3)


def spread_ties(times: np.ndarray, resolution: np.ndarray) -> tuple[np.ndarray, int]:
    """Strictly increasing times from sorted ``times``: a run of n equal stamps becomes
    ``t + k * resolution / n`` (k = 0..n-1). Returns the new times and how many frames moved."""
    times = np.asarray(times, float).copy()
    moved = 0
    i = 0
    while i < len(times):
        j = i
        while j + 1 < len(times) and times[j + 1] == times[i]:
            j += 1
        n = j - i + 1
        if n > 1:
            times[i : j + 1] = times[i] + np.arange(n) * (resolution[i] / n)
            moved += n - 1
        i = j + 1
    return times, moved


def _counts_text(counts: Counter) -> str:
    return ", ".join(f"{k} ({n})" for k, n in counts.most_common())


def _one_line(text: str) -> str:
    return " ".join(text.split())


@dataclass
class Geotag:
    """What one image file says about itself."""

    path: Path
    width: int
    height: int
    latitude: float
    longitude: float
    altitude: float | None
    times: dict[str, tuple[float, float, str]]  # source -> (seconds, resolution, text)
    yaw_deg: float | None
    yaw_source: str | None
    height_agl: float | None
    roll_deg: float | None
    pitch_deg: float | None
    focal_mm: float | None
    sensor_width_mm: float | None


def _num(spec: oiio.ImageSpec, name: str) -> float | None:
    v = spec.getattribute(name)
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return None


def read_geotag(path: str | Path) -> Geotag:
    """Read the geotag and camera metadata of one image (header only, no pixels).

    Raises:
        BadInput: unreadable file, or no (or malformed) EXIF GPS latitude/longitude.
    """
    path = Path(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise BadInput(path, f"unreadable image: {_one_line(oiio.geterror() or 'cannot open')}")
    try:
        spec = inp.spec()
    finally:
        inp.close()
    coords = {}
    for axis, pos, neg in (("Latitude", "N", "S"), ("Longitude", "E", "W")):
        v = spec.getattribute(f"GPS:{axis}")
        if v is None:
            raise BadInput(f"{path}[GPS:{axis}]", "no EXIF GPS position (the frame is not geotagged)")
        try:
            coords[axis] = dms_to_degrees(v, spec.getattribute(f"GPS:{axis}Ref"), pos, neg)
        except ValueError as e:
            raise BadInput(f"{path}[GPS:{axis}]", str(e)) from None
    if not (-90.0 <= coords["Latitude"] <= 90.0 and -180.0 <= coords["Longitude"] <= 180.0):
        raise BadInput(f"{path}[GPS:Latitude]", f"position {coords['Latitude']}, {coords['Longitude']} is out of range")
    alt = _num(spec, "GPS:Altitude")
    if alt is not None and spec.getattribute("GPS:AltitudeRef") == 1:
        alt = -alt

    times: dict[str, tuple[float, float, str]] = {}
    dto = spec.getattribute("Exif:DateTimeOriginal")
    try:
        if isinstance(dto, str) and dto.strip():
            s, res = _parse_exif_datetime(dto, spec.getattribute("Exif:SubsecTimeOriginal"))
            times[TIME_SOURCES[0]] = (s, res, dto.strip())
    except ValueError:
        raise BadInput(f"{path}[Exif:DateTimeOriginal]", f"unparsable date {dto!r}") from None
    utc = spec.getattribute("sensefly:UTCTime")
    try:
        if isinstance(utc, str) and utc.strip():
            s, res = _parse_iso(utc)
            times[TIME_SOURCES[1]] = (s, res, utc.strip())
    except ValueError:
        raise BadInput(f"{path}[sensefly:UTCTime]", f"unparsable time {utc!r}") from None
    gd, gt = spec.getattribute("GPS:DateStamp"), spec.getattribute("GPS:TimeStamp")
    try:
        if isinstance(gd, str) and gd.strip() and gt is not None:
            s, res = _parse_gps_time(gd, gt)
            times[TIME_SOURCES[2]] = (s, res, f"{gd.strip()} {tuple(gt)}")
    except (ValueError, TypeError):
        raise BadInput(f"{path}[GPS:TimeStamp]", f"unparsable GPS time {gd!r} {gt!r}") from None

    yaw, yaw_source = None, None
    for name in YAW_FIELDS:
        yaw = _num(spec, name)
        if yaw is not None:
            yaw_source = name
            break

    sensor_w = None
    px, res, unit = _num(spec, "Exif:PixelXDimension"), _num(spec, "Exif:FocalPlaneXResolution"), spec.getattribute("Exif:FocalPlaneResolutionUnit")
    if px and res and res > 0 and unit in _RES_UNIT_MM:
        sensor_w = px / res * _RES_UNIT_MM[unit]

    return Geotag(
        path=path,
        width=spec.width,
        height=spec.height,
        latitude=coords["Latitude"],
        longitude=coords["Longitude"],
        altitude=alt,
        times=times,
        yaw_deg=yaw,
        yaw_source=yaw_source,
        height_agl=_num(spec, HEIGHT_FIELD),
        roll_deg=_num(spec, ROLL_FIELD),
        pitch_deg=_num(spec, PITCH_FIELD),
        focal_mm=_num(spec, "Exif:FocalLength"),
        sensor_width_mm=sensor_w,
    )


def order_frames(tags: list[Geotag]) -> tuple[list[Geotag], np.ndarray, str, int, str]:
    """Sort frames in time and give them strictly increasing times.

    Returns ``(sorted tags, t seconds since the first frame, time source, ties spread,
    absolute stamp of the first frame as text)``.
    """
    for source in TIME_SOURCES:
        if all(source in g.times for g in tags):
            order = sorted(range(len(tags)), key=lambda i: (tags[i].times[source][0], tags[i].path.name))
            tags = [tags[i] for i in order]
            raw = np.array([g.times[source][0] for g in tags])
            res = np.array([g.times[source][1] for g in tags])
            t, moved = spread_ties(raw, res)
            return tags, t - t[0], source, moved, tags[0].times[source][2]
    tags = sorted(tags, key=lambda g: g.path.name)
    return tags, np.arange(len(tags), dtype=float), "file name order (1 s steps)", 0, ""


def _resize_to_png(src: Path, dst: Path, width: int, height: int) -> None:
    buf = oiio.ImageBuf(str(src))
    out = oiio.ImageBufAlgo.resize(buf, roi=oiio.ROI(0, width, 0, height, 0, 1, 0, buf.nchannels))
    if out.has_error or not out.write(str(dst), "uint8"):
        raise BadInput(src, f"cannot resize: {_one_line(out.geterror() or buf.geterror())}")


# --- import ------------------------------------------------------------------------------


def import_geotagged(
    image_dir: str | Path,
    out: str | Path,
    *,
    focal_mm: float | None = None,
    sensor_width_mm: float | None = None,
    height_m: float | None = None,
    max_width: int | None = None,
    quiet: bool = True,
) -> dict:
    """Import the geotagged JPEGs of ``image_dir`` as a new drive log ``out``; returns the summary.

    Raises :class:`BadInput` on bad input; nothing is left under ``out`` then.
    """
    t_begin = time.perf_counter()
    image_dir, out = Path(image_dir), Path(out)
    for name, v in (("--focal-mm", focal_mm), ("--sensor-width-mm", sensor_width_mm), ("--height-m", height_m)):
        if v is not None and (not math.isfinite(v) or v <= 0):
            raise BadInput(name, f"must be a positive number, got {v}")
    if max_width is not None and max_width < 2:
        raise BadInput("--max-width", f"must be at least 2 pixels, got {max_width}")
    if not image_dir.is_dir():
        raise BadInput(image_dir, "image folder not found")
    replace = check_out_dir(out)
    files = sorted(p for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise BadInput(image_dir, f"no JPEG images ({', '.join(IMAGE_SUFFIXES)}) in the folder")

    tags = [read_geotag(p) for p in progress(files, label="read geotags", quiet=quiet)]
    for g in tags:
        if g.yaw_deg is None:
            raise BadInput(f"{g.path}[{YAW_FIELDS[0]}]", f"no heading ({', '.join(YAW_FIELDS)} all missing)")
        if g.height_agl is None and height_m is None:
            raise BadInput(f"{g.path}[{HEIGHT_FIELD}]", "no height above ground in the XMP; give --height-m")

    # One frame size for the log.
    sizes = Counter((g.width, g.height) for g in tags)
    best = max(sizes.values())
    width, height = next((g.width, g.height) for g in tags if sizes[(g.width, g.height)] == best)
    kept, dropped, resize = [], [], set()
    for g in tags:
        if (g.width, g.height) != (width, height):
            if abs((g.width / g.height) / (width / height) - 1.0) > ASPECT_TOLERANCE:
                reason = (f"size {g.width} x {g.height} has another aspect ratio than the log's "
                          f"{width} x {height} (the same camera mode cannot be assumed)")
                dropped.append({"image": g.path.name, "reason": reason})
                log.warning("%s: dropped: %s", g.path, reason)
                continue
            resize.add(g.path.name)
        kept.append(g)
    if max_width is not None and width > max_width:
        height = max(1, round(height * max_width / width))
        width = max_width
        resize = {g.path.name for g in kept}
    if len(kept) < 2:
        raise BadInput(image_dir, f"{len(kept)} usable geotagged frame(s), a drive log needs at least 2")

    tags, frame_t, time_source, ties, time_origin = order_frames(kept)
    if ties:
        log.warning("%s: %d frames share a time stamp with another; spread within the stamp's resolution", image_dir, ties)

    # Camera.
    if focal_mm is not None:
        focal, focal_source = float(focal_mm), "--focal-mm"
    else:
        fs = [g.focal_mm for g in tags if g.focal_mm]
        if len(fs) < len(tags):
            g = next(g for g in tags if not g.focal_mm)
            raise BadInput(f"{g.path}[Exif:FocalLength]", "missing; give --focal-mm")
        focal, focal_source = round(float(np.median(fs)), 6), "Exif:FocalLength"  # EXIF rational read as float32
        if max(fs) - min(fs) > 1e-3 * focal:
            raise BadInput(image_dir, f"Exif:FocalLength varies from {min(fs)} to {max(fs)} mm (zoom changed?); give --focal-mm")
    if sensor_width_mm is not None:
        sensor_w, sensor_source = float(sensor_width_mm), "--sensor-width-mm"
    else:
        sw = [g.sensor_width_mm for g in tags if g.sensor_width_mm]
        if len(sw) < len(tags):
            g = next(g for g in tags if not g.sensor_width_mm)
            raise BadInput(f"{g.path}[Exif:FocalPlaneXResolution]", "missing, cannot derive the sensor width; give --sensor-width-mm")
        sensor_w, sensor_source = round(float(np.median(sw)), 6), "Exif:PixelXDimension/Exif:FocalPlaneXResolution"
    fx = focal / sensor_w * width
    heights = np.array([g.height_agl if g.height_agl is not None else height_m for g in tags], float)
    height_sources = Counter(HEIGHT_FIELD if g.height_agl is not None else "--height-m" for g in tags)
    cx, cy = frame_centre((height, width))
    camera = CameraSpec(fx=fx, fy=fx, cx=cx, cy=cy, height_m=float(np.median(heights)))

    # Poses.
    lat = np.array([g.latitude for g in tags])
    lon = np.array([g.longitude for g in tags])
    x, y = local_east_north(lat, lon, lat[0], lon[0])
    yaw = np.array([g.yaw_deg for g in tags])
    odometry = np.column_stack([frame_t, x, y, theta_from_heading(yaw)])

    images = [f"images/{g.path.stem}.png" if g.path.name in resize else f"images/{g.path.name}" for g in tags]
    if len(set(images)) != len(images):
        dup = next(n for n in images if images.count(n) > 1)
        raise BadInput(image_dir, f"two frames would both be stored as {dup!r}")

    source = {
        "kind": "geotagged_images",
        "image_dir": str(image_dir.resolve()),
        "time_source": time_source,
        "time_origin": time_origin,
        "time_ties_spread": ties,
        "projection": "local east/north tangent plane (equirectangular, WGS84 radii at the origin); x east, y north",
        "origin_latitude": float(lat[0]),
        "origin_longitude": float(lon[0]),
        "heading": "theta = -yaw (yaw compass degrees clockwise from north; image top towards the nose)",
        # as text: drivelog's TOML writer does not quote keys such as "sensefly:Heading"
        "yaw_sources": _counts_text(Counter(g.yaw_source for g in tags)),
        "focal_mm": focal,
        "focal_source": focal_source,
        "sensor_width_mm": sensor_w,
        "sensor_width_source": sensor_source,
        "height_m": "median of the per-frame height above ground (frames.csv height_m)",
        "height_sources": _counts_text(height_sources),
        "frames_found": len(files),
        "frames_dropped": [f"{d['image']}: {d['reason']}" for d in dropped],
        "frames_resized": sorted(resize),
    }
    has_attitude = any(g.roll_deg is not None or g.pitch_deg is not None for g in tags)
    if has_attitude:
        source["attitude"] = ATTITUDE_FILE

    with atomic_dir(out, replace=replace) as tmp:
        (tmp / "images").mkdir()
        for g, name in progress(list(zip(tags, images)), label="import-geotagged", quiet=quiet):
            if g.path.name in resize:
                _resize_to_png(g.path, tmp / name, width, height)
            else:
                shutil.copyfile(g.path, tmp / name)
        write_drive_log(tmp, camera, frame_t, images, odometry, log_id=out.name, extra={"source": source})
        # frames.csv again with the per-frame height as an extension column.
        lines = ["t,image,height_m"] + [
            f"{t!r},{img},{h!r}" for t, img, h in zip(frame_t.tolist(), images, heights.tolist())
        ]
        write_text_atomic(tmp / "frames.csv", "\n".join(lines) + "\n")
        if has_attitude:
            def rad(v: float | None) -> str:
                return repr(math.radians(v)) if v is not None else "nan"

            lines = ["t,roll,pitch,yaw"] + [
                f"{t!r},{rad(g.roll_deg)},{rad(g.pitch_deg)},{rad(g.yaw_deg)}" for t, g in zip(frame_t.tolist(), tags)
            ]
            write_text_atomic(tmp / ATTITUDE_FILE, "\n".join(lines) + "\n")
        try:
            read_drive_log(tmp)
        except BadInput as e:
            raise JobFailed(f"{out}: the written drive log does not validate: {e}") from None

    steps = np.hypot(np.diff(x), np.diff(y))
    return {
        "image_dir": str(image_dir),
        "out": str(out),
        "frames": len(tags),
        "frames_found": len(files),
        "frames_dropped": dropped,
        "frames_resized": len(resize),
        "width": width,
        "height": height,
        "time_source": time_source,
        "time_ties_spread": ties,
        "yaw_sources": dict(Counter(g.yaw_source for g in tags)),
        "height_sources": dict(height_sources),
        "focal_mm": focal,
        "focal_source": focal_source,
        "sensor_width_mm": sensor_w,
        "sensor_width_source": sensor_source,
        "fx": fx,
        "height_m": camera.height_m,
        "height_min_m": float(heights.min()),
        "height_max_m": float(heights.max()),
        "ground_pixel_size_m": camera.height_m / fx,
        "origin_latitude": float(lat[0]),
        "origin_longitude": float(lon[0]),
        "extent_m": [float(x.max() - x.min()), float(y.max() - y.min())],
        "path_length_m": float(steps.sum()),
        "seconds": time.perf_counter() - t_begin,
    }


def summary_line(s: dict) -> str:
    dropped = f", {len(s['frames_dropped'])} dropped" if s["frames_dropped"] else ""
    resized = f", {s['frames_resized']} resized" if s["frames_resized"] else ""
    return (
        f"import-geotagged: {s['frames']} of {s['frames_found']} frames{dropped}{resized}, "
        f"{s['width']} x {s['height']} px, height {s['height_m']:.1f} m (median), "
        f"~{s['ground_pixel_size_m']:.3f} m/px, extent {s['extent_m'][0]:.0f} x {s['extent_m'][1]:.0f} m, "
        f"times from {s['time_source']} -> {s['out']}"
    )


@click.command("import-geotagged")
@click.argument("image_dir", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--focal-mm", type=float, default=None, help="Focal length in mm (default: Exif:FocalLength).")
@click.option("--sensor-width-mm", type=float, default=None,
              help="Sensor width in mm (default: from Exif:PixelXDimension / Exif:FocalPlaneXResolution).")
@click.option("--height-m", type=float, default=None,
              help="Height above ground in metres for frames without XMP sensefly:Height.")
@click.option("--max-width", type=int, default=None, help="Downscale frames wider than this many pixels.")
@config_option
@report_option
@quiet_option
def import_geotagged_cmd(image_dir: Path, out: Path, focal_mm, sensor_width_mm, height_m, max_width, config_file, report, quiet) -> None:
    """Import a folder IMAGE_DIR of geotagged aerial JPEGs as a drive log OUT.

    Frames in time order; odometry = GPS positions in a local east/north frame (metres)
    with theta from the camera heading; camera intrinsics from the focal length, sensor
    width and the median height above ground.
    """
    setup(config_file, quiet)
    summary = import_geotagged(
        image_dir, out, focal_mm=focal_mm, sensor_width_mm=sensor_width_mm, height_m=height_m,
        max_width=max_width, quiet=quiet,
    )
    write_report(report, summary)
    click.echo(summary_line(summary))
