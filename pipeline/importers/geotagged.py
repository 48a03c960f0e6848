"""``mosaicmap import-geotagged``: a folder of geotagged aerial JPEGs -> drive log v1.

For nadir(-ish) frames from a drone or aircraft whose JPEGs carry EXIF GPS and, ideally,
the autopilot's XMP record: senseFly (``sensefly:Height`` above ground, ``sensefly:Heading``,
``sensefly:PitchAngle``, ``sensefly:RollAngle``, ``sensefly:UTCTime``) or DJI
(``drone-dji:GimbalYawDegree``, ``GimbalPitchDegree``, ``GimbalRollDegree``,
``FlightYawDegree``, ``FlightPitchDegree``, ``FlightRollDegree``, ``RelativeAltitude``,
``AbsoluteAltitude``). All metadata is read with OpenImageIO, which presents EXIF as
``Exif:*`` / ``GPS:*`` and XMP as ``<namespace prefix>:<name>`` attributes of the image spec
(XMP properties written as elements or as attributes of ``rdf:Description``, as DJI does,
alike; DJI's signed strings such as ``"+35.20"`` arrive as numbers, and a number given as
text is parsed too).

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
    The yaw is a compass heading of the camera (degrees clockwise from north, the image
    top's direction). Per frame, unless an option overrides it, the first present of
    ``drone-dji:GimbalYawDegree`` (the gimbal: the camera's own orientation),
    ``drone-dji:FlightYawDegree`` (the aircraft's nose), ``sensefly:Heading``,
    ``GPS:ImgDirection``, ``GPS:Track`` (direction of travel) (:data:`YAW_FIELDS`).
    ``--heading-deg DEG`` gives every frame the fixed yaw DEG instead; ``--heading-from
    track`` derives every frame's yaw from the GPS track (:func:`track_headings`: the
    direction from the nearest earlier to the nearest later frame at least
    :data:`TRACK_MIN_STEP_M` away, one-sided at the ends; a nose-forward assumption, off by
    up to 45 degrees at the frames of a sharp turn). The camera is mounted with the image
    *top* towards the yaw direction, so the image's column axis (the vehicle +x of
    :mod:`mapstore.grid`) points at compass ``yaw + 90`` degrees, i.e. counter-clockwise
    from east ``90 - (yaw + 90) = -yaw``: ``theta = -yaw`` (:func:`theta_from_heading`), for
    every source alike (DJI's yaws are degrees clockwise from north like
    ``sensefly:Heading``). Verified on the Seneca flight: for 86
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
    ``Exif:FocalLength``. ``sensor_width_mm``: ``--sensor-width-mm``, else per frame from
    ``Exif:PixelXDimension / Exif:FocalPlaneXResolution`` (with its resolution unit), else
    from the 35 mm equivalent focal length ``Exif:FocalLengthIn35mmFilm`` (exiftool's
    ``FocalLengthIn35mmFormat``): ``sensor_width_mm = 36 * focal_mm / focal35_mm``, taking
    the 35 mm format's 36 mm *width* as the reference (DJI's convention: 8.8 mm at 24 mm
    equivalent gives the 13.2 mm of a 1" sensor; a camera that scales by the diagonal
    instead, as CIPA DC-008 defines it, would come out 4 % wider on a 4:3 sensor);
    ``focal_mm`` there is the frame's ``Exif:FocalLength``, else ``--focal-mm``. The median
    over the frames is used; the report's ``sensor_width_source`` names the source(s).
    Height above ground per frame: ``sensefly:Height``, else ``drone-dji:RelativeAltitude``
    (the height above the *take-off point*: taken as height above ground, which assumes a
    flat site level with the take-off point; the report's ``height_assumption`` says so),
    else ``--height-m`` (a fallback: frames with their own height keep it). Heights that
    are not positive are ignored (a frame on the ground, or below the take-off point).

Missing metadata
    Every frame is checked for every field the log needs (GPS position, heading, height
    above ground, focal length, sensor width) before anything is written, and one
    :class:`BadInput` (exit 2) lists on one line each missing field with the number of
    frames lacking it, an example file and the option that supplies it, e.g.
    ``IMAGE_DIR: missing metadata: heading in 12 of 12 frames (no ...; e.g. DJI_0001.JPG;
    give --heading-deg DEG or --heading-from track), height above ground in 12 of 12
    frames (...; give --height-m M)``.

Extension files and columns (optional; drive log v1 allows them)
    ``frames.csv`` has an extra column ``height_m`` (the frame's own height above ground:
    it varies by about +-10 % over a flight; drive.toml holds the median). Ingest rectifies
    each frame at its own height, adjusted to the images' relative scale, and turns it to a
    nadir view with the tilt it measures from the images (``[ingest.ground_plane]``).
    ``attitude.csv`` (``t,roll,pitch,yaw``, radians, ``nan`` where absent) is written when
    any frame has roll or pitch, as a record: the build does not read it (on the senseFly
    flight the recorded roll and pitch explained the images' tilt far worse than the images
    themselves: 7.2 px of misfit between consecutive frames against 1.4 px). ``yaw`` is the
    compass yaw used for theta (clockwise from north). ``roll`` and ``pitch`` are the
    camera's tilt in the convention of a camera fixed nadir-looking under an aircraft
    (senseFly's, which gives the aircraft's ``sensefly:RollAngle`` / ``PitchAngle``):
    pitch is the tilt from nadir, positive when the camera looks ahead of nadir towards the
    image top (an aircraft's nose-up pitch), roll positive right side down. From DJI's
    gimbal, whose pitch is -90 degrees at nadir: ``pitch = GimbalPitchDegree + 90``,
    ``roll = GimbalRollDegree``. Per frame the first present of the gimbal
    (``drone-dji:GimbalPitchDegree/GimbalRollDegree``), senseFly's, and DJI's aircraft
    attitude (``drone-dji:FlightPitchDegree/FlightRollDegree``, for a camera without a
    gimbal record).

Images
    Copied byte for byte (no recompression) as ``images/<file name>``. All frames of a log
    must have one size: the most common size wins; a frame of another size with the same
    aspect ratio (within 1 %) is resized to it, a frame of another aspect ratio is dropped
    with the reason (both listed in the report and in ``[source]``). With ``--max-width PX``
    wider frames are downscaled. Resized frames are written as lossless PNG
    (``images/<stem>.png``) to avoid a second JPEG generation.

Report keys (``--report FILE``): ``image_dir``, ``out``, ``frames``, ``frames_found``,
``frames_dropped`` (list of ``{image, reason}``), ``frames_resized``, ``width``, ``height``,
``time_source``, ``time_ties_spread``, ``heading_from`` (``metadata``, ``fixed`` or
``track``), ``yaw_sources`` (source -> count), ``height_sources`` (source -> count),
``height_assumption`` (text when ``drone-dji:RelativeAltitude`` was used, else null),
``attitude_sources`` (source -> count of frames with roll or pitch), ``focal_mm``,
``focal_source``, ``sensor_width_mm``, ``sensor_width_source``, ``fx``, ``height_m``
(median), ``height_min_m``, ``height_max_m``, ``ground_pixel_size_m`` (median height /
fx), ``origin_latitude``, ``origin_longitude``, ``extent_m`` ([east span, north span]),
``path_length_m``, ``seconds``.
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

import numpy as np
import OpenImageIO as oiio

from mapstore.grid import GEO_PROJECTION, GeoReference, frame_centre, wrap_angle
from pipeline.drivelog import CameraSpec, read_drive_log, write_drive_log
from pipeline.errors import BadInput, JobFailed
from pipeline.fsutil import atomic_dir, write_text_atomic
from pipeline.images import check_image_header, check_image_size
from pipeline.importers.tiles import check_out_dir
from pipeline.progress import progress

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg")
ATTITUDE_FILE = "attitude.csv"

# Frames whose aspect ratio differs from the log's by less than this are resized to the
# log's size; others are dropped.
ASPECT_TOLERANCE = 0.01

# EXIF FocalPlaneResolutionUnit -> millimetres per unit (1 = none, taken as inch by EXIF).
_RES_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}

# Heading sources, in order of preference (all compass degrees, clockwise from north).
YAW_FIELDS = ("drone-dji:GimbalYawDegree", "drone-dji:FlightYawDegree", "sensefly:Heading", "GPS:ImgDirection", "GPS:Track")
# Height above ground, in order of preference (metres; DJI's is above the take-off point).
HEIGHT_FIELDS = ("sensefly:Height", "drone-dji:RelativeAltitude")
RELATIVE_ALTITUDE = "drone-dji:RelativeAltitude"
HEIGHT_ASSUMPTION = ("drone-dji:RelativeAltitude is the height above the take-off point, used as the height "
                     "above ground: this assumes a flat site level with the take-off point")
# Camera attitude sources, in order of preference: (name, pitch field, roll field, pitch
# offset in degrees that makes the pitch a tilt from nadir).
ATTITUDE_SOURCES = (
    ("drone-dji:Gimbal", "drone-dji:GimbalPitchDegree", "drone-dji:GimbalRollDegree", 90.0),
    ("sensefly", "sensefly:PitchAngle", "sensefly:RollAngle", 0.0),
    ("drone-dji:Flight", "drone-dji:FlightPitchDegree", "drone-dji:FlightRollDegree", 0.0),
)
# The 35 mm equivalent focal length (OpenImageIO's name first, exiftool's second).
FOCAL35_FIELDS = ("Exif:FocalLengthIn35mmFilm", "Exif:FocalLengthIn35mmFormat")
# Width of the 35 mm format (mm) that the equivalent focal length is taken to scale.
FULL_FRAME_WIDTH_MM = 36.0
TIME_SOURCES = ("Exif:DateTimeOriginal", "sensefly:UTCTime", "GPS:DateStamp+GPS:TimeStamp")
# --heading-from track: a frame's direction is taken over neighbours at least this far away
# (metres), so that GPS jitter of a hovering aircraft does not set it.
TRACK_MIN_STEP_M = 1.0

# The prior's error model written to drive.toml [odometry] (pipeline/odometry_model.py): GPS
# positions are absolute, each frame's own, not steps of a dead reckoning. A consumer
# receiver's ~3 m; the heading (compass / autopilot yaw) held loosely, 1 rad: on the senseFly
# flight it was off the images' by up to 0.6 rad in places, and the links set the frames'
# relative rotations. As relative steps (the build's default model) the map's orientation
# rested on the first frame's heading alone: its link groups came out 0.34 rad off the GPS
# positions; as absolute priors 0.000 rad, one group of 146 frames instead of 8, 381 links
# instead of 236, 18 frames without a link instead of 29 (2026-12-02 23:55 UTC).
GPS_ODOMETRY_MODEL = {"kind": "absolute", "sigma_m": 3.0, "heading_sigma_rad": 1.0}

SENSOR_FROM_FOCAL_PLANE = "Exif:PixelXDimension/Exif:FocalPlaneXResolution"
SENSOR_FROM_35MM = "36 mm * Exif:FocalLength / Exif:FocalLengthIn35mmFilm"


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
    return GeoReference(lat0, lon0).from_wgs84(lat, lon)


def theta_from_heading(yaw_deg: np.ndarray | float) -> np.ndarray | float:
    """Pose heading theta (radians, CCW from +x = east) of a frame from its compass yaw (degrees CW from north).

    The image top points to the yaw direction (the nose, or the gimbal's heading), so the
    image column axis (vehicle +x) is at compass ``yaw + 90``: ``theta = 90 - (yaw + 90) = -yaw``.
    """
    return wrap_angle(-np.radians(yaw_deg))


def track_headings(x: np.ndarray, y: np.ndarray, min_step_m: float = TRACK_MIN_STEP_M) -> np.ndarray:
    """Compass yaw (degrees clockwise from north, in [0, 360)) of each frame from the GPS track.

    ``x, y``: east, north positions (metres) in time order. Frame i's direction is from the
    nearest earlier frame at least ``min_step_m`` away to the nearest later one (a central
    difference; one-sided when one of them does not exist). A frame with neither (every
    other frame within ``min_step_m``) takes the yaw of the nearest frame that has one.

    Raises:
        ValueError: no two frames are ``min_step_m`` apart (the track has no direction).
    """
    p = np.column_stack([np.asarray(x, float), np.asarray(y, float)])
    n = len(p)
    yaw = np.full(n, np.nan)
    for i in range(n):
        d = np.hypot(*(p - p[i]).T)
        far = np.flatnonzero(d >= min_step_m)
        before, after = far[far < i], far[far > i]
        a = p[before[-1]] if len(before) else p[i]
        b = p[after[0]] if len(after) else p[i]
        if len(before) or len(after):
            yaw[i] = math.degrees(math.atan2(b[0] - a[0], b[1] - a[1])) % 360.0
    ok = np.flatnonzero(np.isfinite(yaw))
    if len(ok) == 0:
        raise ValueError(f"no two frames are {min_step_m:g} m apart")
    for i in np.flatnonzero(~np.isfinite(yaw)):
        yaw[i] = yaw[ok[np.argmin(np.abs(ok - i))]]
    return yaw


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
    """What one image file says about itself (angles in degrees, lengths in metres or mm as named)."""

    path: Path
    width: int
    height: int
    latitude: float | None  # None: no EXIF GPS position
    longitude: float | None
    altitude: float | None  # metres above sea level (GPS:Altitude, else drone-dji:AbsoluteAltitude)
    times: dict[str, tuple[float, float, str]]  # source -> (seconds, resolution, text)
    yaw_deg: float | None  # compass, clockwise from north
    yaw_source: str | None
    height_agl: float | None  # metres above ground (> 0)
    roll_deg: float | None  # camera roll, positive right side down
    pitch_deg: float | None  # camera tilt from nadir, positive towards the image top
    focal_mm: float | None
    sensor_width_mm: float | None  # from the focal plane resolution
    height_source: str | None = None
    attitude_source: str | None = None
    focal35_mm: float | None = None  # 35 mm equivalent focal length


def _num(spec: oiio.ImageSpec, name: str) -> float | None:
    """Attribute ``name`` as a finite float (a number, or text such as DJI's ``"+35.20"``), else None."""
    v = spec.getattribute(name)
    if isinstance(v, str):
        try:
            v = float(v.strip())
        except ValueError:
            return None
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return None


def _first(spec: oiio.ImageSpec, names: tuple[str, ...], *, positive: bool = False) -> tuple[float | None, str | None]:
    for name in names:
        v = _num(spec, name)
        if v is not None and (v > 0 or not positive):
            return v, name
    return None, None


def read_geotag(path: str | Path) -> Geotag:
    """Read the geotag and camera metadata of one image (header only, no pixels).

    A missing field is None (the import reports all of them at once).

    Raises:
        BadInput: unreadable file, or a malformed EXIF GPS position or date.
    """
    path = Path(path)
    check_image_size(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise BadInput(path, f"unreadable image: {_one_line(oiio.geterror() or 'cannot open')}")
    try:
        spec = inp.spec()
        check_image_header(path, spec)  # the import decodes it later: the caps hold before that
    finally:
        inp.close()
    coords: dict[str, float | None] = {"Latitude": None, "Longitude": None}
    if spec.getattribute("GPS:Latitude") is not None or spec.getattribute("GPS:Longitude") is not None:
        for axis, pos, neg in (("Latitude", "N", "S"), ("Longitude", "E", "W")):
            v = spec.getattribute(f"GPS:{axis}")
            if v is None:
                raise BadInput(f"{path}[GPS:{axis}]", "missing while the other GPS coordinate is present")
            try:
                coords[axis] = dms_to_degrees(v, spec.getattribute(f"GPS:{axis}Ref"), pos, neg)
            except ValueError as e:
                raise BadInput(f"{path}[GPS:{axis}]", str(e)) from None
        if not (-90.0 <= coords["Latitude"] <= 90.0 and -180.0 <= coords["Longitude"] <= 180.0):
            raise BadInput(f"{path}[GPS:Latitude]", f"position {coords['Latitude']}, {coords['Longitude']} is out of range")
    alt = _num(spec, "GPS:Altitude")
    if alt is not None and spec.getattribute("GPS:AltitudeRef") == 1:
        alt = -alt
    if alt is None:
        alt = _num(spec, "drone-dji:AbsoluteAltitude")

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

    yaw, yaw_source = _first(spec, YAW_FIELDS)
    height_agl, height_source = _first(spec, HEIGHT_FIELDS, positive=True)

    roll = pitch = None
    attitude_source = None
    for name, pitch_field, roll_field, offset in ATTITUDE_SOURCES:
        p, r = _num(spec, pitch_field), _num(spec, roll_field)
        if p is not None or r is not None:
            pitch = p + offset if p is not None else None
            roll, attitude_source = r, name
            break

    sensor_w = None
    px, res, unit = _num(spec, "Exif:PixelXDimension"), _num(spec, "Exif:FocalPlaneXResolution"), spec.getattribute("Exif:FocalPlaneResolutionUnit")
    if px and res and res > 0 and unit in _RES_UNIT_MM:
        sensor_w = px / res * _RES_UNIT_MM[unit]
    focal = _num(spec, "Exif:FocalLength")
    focal35, _ = _first(spec, FOCAL35_FIELDS, positive=True)

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
        height_agl=height_agl,
        height_source=height_source,
        roll_deg=roll,
        pitch_deg=pitch,
        attitude_source=attitude_source,
        focal_mm=focal if focal and focal > 0 else None,
        focal35_mm=focal35,
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
    check_image_size(src)
    buf = oiio.ImageBuf(str(src))
    if not buf.has_error:
        check_image_header(src, buf.spec())
    out = oiio.ImageBufAlgo.resize(buf, roi=oiio.ROI(0, width, 0, height, 0, 1, 0, buf.nchannels))
    if out.has_error or not out.write(str(dst), "uint8"):
        raise BadInput(src, f"cannot resize: {_one_line(out.geterror() or buf.geterror())}")


class MetadataCheck:
    """Collects the frames lacking each needed field, to report them all in one line."""

    def __init__(self, frames: int):
        self.frames = frames
        self.missing: list[str] = []
        self.other: list[str] = []

    def lacking(self, what: str, tags: list[Geotag], looked_for: str, remedy: str) -> None:
        """``tags`` lack ``what`` (none of ``looked_for``); ``remedy`` says which option supplies it."""
        if tags:
            self.missing.append(f"{what} in {len(tags)} of {self.frames} frames "
                                f"({looked_for}; e.g. {tags[0].path.name}; {remedy})")

    def problem(self, text: str) -> None:
        self.other.append(text)

    def raise_if_any(self, where: Path) -> None:
        parts = []
        if self.missing:
            parts.append("missing metadata: " + ", ".join(self.missing))
        parts.extend(self.other)
        if parts:
            raise BadInput(where, _one_line("; ".join(parts)))


# --- import ------------------------------------------------------------------------------

HEADING_FROM = ("metadata", "track")


def _check_options(focal_mm: float | None, sensor_width_mm: float | None, height_m: float | None,
                   heading_deg: float | None, heading_from: str, max_width: int | None) -> None:
    """BadInput naming the option when one is out of range or two conflict."""
    for name, v in (("--focal-mm", focal_mm), ("--sensor-width-mm", sensor_width_mm), ("--height-m", height_m)):
        if v is not None and (not math.isfinite(v) or v <= 0):
            raise BadInput(name, f"must be a positive number, got {v}")
    if heading_deg is not None and not math.isfinite(heading_deg):
        raise BadInput("--heading-deg", f"must be a finite compass heading in degrees, got {heading_deg}")
    if heading_from not in HEADING_FROM:
        raise BadInput("--heading-from", f"must be one of {', '.join(HEADING_FROM)}, got {heading_from!r}")
    if heading_deg is not None and heading_from != "metadata":
        raise BadInput("--heading-deg", f"give either --heading-deg or --heading-from {heading_from}, not both")
    if max_width is not None and max_width < 2:
        raise BadInput("--max-width", f"must be at least 2 pixels, got {max_width}")


def _image_files(image_dir: Path) -> list[Path]:
    """The folder's JPEGs (not recursive), sorted by path; BadInput when there is none."""
    files = sorted(p for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise BadInput(image_dir, f"no JPEG images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return files


@dataclass
class _Sizes:
    """One frame size for the log: the frames kept, those dropped (``{image, reason}``), the
    file names to resize, and the log's size (pixels)."""

    kept: list[Geotag]
    dropped: list[dict]
    resize: set[str]
    width: int
    height: int


def _one_size(tags: list[Geotag], max_width: int | None, image_dir: Path) -> _Sizes:
    """The most common size wins; frames of its aspect ratio are resized to it, others dropped;
    ``max_width`` (pixels) downscales wider logs."""
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
        raise BadInput(image_dir, f"{len(kept)} usable frame(s) of one size, a drive log needs at least 2")
    return _Sizes(kept, dropped, resize, width, height)


@dataclass
class _Metadata:
    """What the log needs from the frames' metadata, per sorted frame: GPS (degrees) and its
    local east/north (metres), the compass yaw (degrees clockwise from north) and where each
    came from, the focal length and sensor width (mm) and their sources."""

    lat: np.ndarray | None
    lon: np.ndarray | None
    x: np.ndarray | None
    y: np.ndarray | None
    heading_mode: str
    yaw: np.ndarray | None
    yaw_sources: Counter
    focal: float | None
    focal_source: str | None
    sensor_w: float | None
    sensor_source: str | None


def _positions(tags: list[Geotag], check: MetadataCheck):
    """(lat, lon, x, y): degrees and local east/north metres around the first frame, or
    Nones when a frame lacks GPS (recorded in ``check``)."""
    check.lacking("GPS position", [g for g in tags if g.latitude is None],
                  "no GPS:Latitude/GPS:Longitude", "no option supplies it: geotag or remove those frames")
    if not all(g.latitude is not None for g in tags):
        return None, None, None, None
    lat = np.array([g.latitude for g in tags])
    lon = np.array([g.longitude for g in tags])
    x, y = local_east_north(lat, lon, lat[0], lon[0])
    return lat, lon, x, y


def _headings(tags: list[Geotag], check: MetadataCheck, x: np.ndarray | None, y: np.ndarray | None,
              heading_deg: float | None, heading_from: str) -> tuple[str, np.ndarray | None, Counter]:
    """(mode, yaw, sources): compass degrees clockwise from north per frame, fixed, from the
    GPS track or from the metadata."""
    if heading_deg is not None:
        heading_mode = "fixed"
        yaw = np.full(len(tags), float(heading_deg) % 360.0)
        yaw_sources = Counter({"--heading-deg": len(tags)})
    elif heading_from == "track":
        heading_mode = "track"
        yaw = None
        yaw_sources = Counter({"--heading-from track": len(tags)})
        if x is not None:
            try:
                yaw = track_headings(x, y)
            except ValueError as e:
                check.problem(f"--heading-from track: {e} (the GPS track has no direction; give --heading-deg)")
    else:
        heading_mode = "metadata"
        check.lacking("heading", [g for g in tags if g.yaw_deg is None],
                      f"no {', '.join(YAW_FIELDS[:-1])} or {YAW_FIELDS[-1]}",
                      "give --heading-deg DEG or --heading-from track")
        yaw = np.array([g.yaw_deg if g.yaw_deg is not None else np.nan for g in tags])
        yaw_sources = Counter(g.yaw_source for g in tags if g.yaw_source)
    return heading_mode, yaw, yaw_sources


def _focal_length(tags: list[Geotag], check: MetadataCheck, focal_mm: float | None) -> tuple[float | None, str | None]:
    """(focal length mm, source): the option's, else the frames' one ``Exif:FocalLength``."""
    focal, focal_source = None, None
    if focal_mm is not None:
        focal, focal_source = float(focal_mm), "--focal-mm"
    else:
        check.lacking("focal length", [g for g in tags if not g.focal_mm], "no Exif:FocalLength", "give --focal-mm MM")
        fs = [g.focal_mm for g in tags if g.focal_mm]
        if len(fs) == len(tags):
            focal, focal_source = round(float(np.median(fs)), 6), "Exif:FocalLength"  # EXIF rational read as float32
            if max(fs) - min(fs) > 1e-3 * focal:
                check.problem(f"Exif:FocalLength varies from {min(fs)} to {max(fs)} mm (zoom changed?); give --focal-mm")
    return focal, focal_source


def _sensor_width(tags: list[Geotag], check: MetadataCheck, focal_mm: float | None,
                  sensor_width_mm: float | None) -> tuple[float | None, str | None]:
    """(sensor width mm, source): the option's, else the median of the frames' (focal plane
    resolution, or 35 mm equivalent focal length)."""
    sensor_w, sensor_source = None, None
    if sensor_width_mm is not None:
        sensor_w, sensor_source = float(sensor_width_mm), "--sensor-width-mm"
    else:
        widths: list[tuple[float, str] | None] = []
        for g in tags:
            f = g.focal_mm or focal_mm
            if g.sensor_width_mm:
                widths.append((g.sensor_width_mm, SENSOR_FROM_FOCAL_PLANE))
            elif g.focal35_mm and f:
                widths.append((FULL_FRAME_WIDTH_MM * f / g.focal35_mm, SENSOR_FROM_35MM))
            else:
                widths.append(None)
        check.lacking("sensor width", [g for g, w in zip(tags, widths) if w is None],
                      "no Exif:FocalPlaneXResolution, nor Exif:FocalLengthIn35mmFilm with a focal length",
                      "give --sensor-width-mm MM")
        if all(widths):
            sensor_w = round(float(np.median([w for w, _ in widths])), 6)
            kinds = Counter(s for _, s in widths)
            sensor_source = next(iter(kinds)) if len(kinds) == 1 else _counts_text(kinds)
    return sensor_w, sensor_source


def _metadata(tags: list[Geotag], image_dir: Path, *, focal_mm: float | None, sensor_width_mm: float | None,
              height_m: float | None, heading_deg: float | None, heading_from: str) -> _Metadata:
    """Every field the log needs, checked on every frame: one BadInput listing all that is
    missing (see the module docstring)."""
    check = MetadataCheck(len(tags))
    lat, lon, x, y = _positions(tags, check)
    heading_mode, yaw, yaw_sources = _headings(tags, check, x, y, heading_deg, heading_from)
    # Height above ground (metres): the frame's own, else --height-m.
    check.lacking("height above ground",
                  [g for g in tags if g.height_agl is None] if height_m is None else [],
                  f"no positive {' or '.join(HEIGHT_FIELDS)}", "give --height-m M")
    focal, focal_source = _focal_length(tags, check, focal_mm)
    sensor_w, sensor_source = _sensor_width(tags, check, focal_mm, sensor_width_mm)
    check.raise_if_any(image_dir)
    return _Metadata(lat, lon, x, y, heading_mode, yaw, yaw_sources, focal, focal_source, sensor_w, sensor_source)


@dataclass
class _Heights:
    """Per frame height above ground (metres) and where each came from; the caveat text
    when a height above the take-off point was used."""

    heights: np.ndarray
    sources: Counter
    assumption: str | None


def _heights(tags: list[Geotag], height_m: float | None, image_dir: Path) -> _Heights:
    heights = np.array([g.height_agl if g.height_agl is not None else height_m for g in tags], float)
    height_sources = Counter(g.height_source if g.height_agl is not None else "--height-m" for g in tags)
    height_assumption = HEIGHT_ASSUMPTION if RELATIVE_ALTITUDE in height_sources else None
    if height_assumption:
        log.warning("%s: %d frames: %s", image_dir, height_sources[RELATIVE_ALTITUDE], height_assumption)
    return _Heights(heights, height_sources, height_assumption)


def _image_names(tags: list[Geotag], resize: set[str], image_dir: Path) -> list[str]:
    """Each frame's file in the log (``images/<name>``, ``.png`` when resized); distinct."""
    images = [f"images/{g.path.stem}.png" if g.path.name in resize else f"images/{g.path.name}" for g in tags]
    if len(set(images)) != len(images):
        dup = next(n for n in images if images.count(n) > 1)
        raise BadInput(image_dir, f"two frames would both be stored as {dup!r}")
    return images


def _source_table(image_dir: Path, tags: list[Geotag], files: list[Path], sz: _Sizes, meta: _Metadata,
                  hts: _Heights, attitude_sources: Counter, *, time_source: str, time_origin: str, ties: int,
                  heading_deg: float | None) -> dict:
    """drive.toml's ``[source]`` table."""
    source = {
        "kind": "geotagged_images",
        "image_dir": str(image_dir.resolve()),
        "time_source": time_source,
        "time_origin": time_origin,
        "time_ties_spread": ties,
        "projection": GEO_PROJECTION,
        "origin_latitude": float(meta.lat[0]),
        "origin_longitude": float(meta.lon[0]),
        "heading": "theta = -yaw (yaw compass degrees clockwise from north; image top towards the yaw)",
        "heading_from": meta.heading_mode,
        # as text: drivelog's TOML writer does not quote keys such as "sensefly:Heading"
        "yaw_sources": _counts_text(meta.yaw_sources),
        "focal_mm": meta.focal,
        "focal_source": meta.focal_source,
        "sensor_width_mm": meta.sensor_w,
        "sensor_width_source": meta.sensor_source,
        "height_m": "median of the per-frame height above ground (frames.csv height_m)",
        "height_sources": _counts_text(hts.sources),
        "frames_found": len(files),
        "frames_dropped": [f"{d['image']}: {d['reason']}" for d in sz.dropped],
        "frames_resized": sorted(sz.resize),
    }
    if meta.heading_mode == "fixed":
        source["heading_deg"] = float(heading_deg)
    if hts.assumption:
        source["height_assumption"] = hts.assumption
    if _has_attitude(tags):
        source["attitude"] = ATTITUDE_FILE
        source["attitude_convention"] = (
            "t,roll,pitch,yaw in radians; pitch = camera tilt from nadir, positive towards the image top "
            "(DJI: GimbalPitchDegree + 90), roll positive right side down, yaw = the compass yaw used for theta")
        source["attitude_sources"] = _counts_text(attitude_sources)
    return source


def _has_attitude(tags: list[Geotag]) -> bool:
    return any(g.roll_deg is not None or g.pitch_deg is not None for g in tags)


def _write_log(out: Path, replace: bool, tags: list[Geotag], images: list[str], sz: _Sizes, camera: CameraSpec,
               frame_t: np.ndarray, odometry: np.ndarray, heights: np.ndarray, yaw: np.ndarray, source: dict,
               quiet: bool) -> None:
    """The drive log, atomically: the images (copied, or resized to PNG), drive.toml,
    odometry.csv, frames.csv with the per-frame height, attitude.csv when any frame has one;
    then read back with drivelog's rules."""
    with atomic_dir(out, replace=replace) as tmp:
        (tmp / "images").mkdir()
        for g, name in progress(list(zip(tags, images)), label="import-geotagged", unit="frames", quiet=quiet):
            if g.path.name in sz.resize:
                _resize_to_png(g.path, tmp / name, sz.width, sz.height)
            else:
                shutil.copyfile(g.path, tmp / name)
        write_drive_log(tmp, camera, frame_t, images, odometry, log_id=out.name,
                        extra={"odometry": dict(GPS_ODOMETRY_MODEL), "source": source})
        # frames.csv again with the per-frame height as an extension column.
        lines = ["t,image,height_m"] + [
            f"{t!r},{img},{h!r}" for t, img, h in zip(frame_t.tolist(), images, heights.tolist())
        ]
        write_text_atomic(tmp / "frames.csv", "\n".join(lines) + "\n")
        if _has_attitude(tags):
            def rad(v: float | None) -> str:
                return repr(math.radians(v)) if v is not None else "nan"

            lines = ["t,roll,pitch,yaw"] + [
                f"{t!r},{rad(g.roll_deg)},{rad(g.pitch_deg)},{rad(w)}"
                for t, g, w in zip(frame_t.tolist(), tags, yaw.tolist())
            ]
            write_text_atomic(tmp / ATTITUDE_FILE, "\n".join(lines) + "\n")
        try:
            read_drive_log(tmp)
        except BadInput as e:
            raise JobFailed(f"{out}: the written drive log does not validate: {e}") from None


def _summary(image_dir: Path, out: Path, files: list[Path], tags: list[Geotag], sz: _Sizes, meta: _Metadata,
             hts: _Heights, camera: CameraSpec, attitude_sources: Counter, *, fx: float, time_source: str,
             ties: int, t_begin: float) -> dict:
    """The report (see the module docstring; ``fx``: pixels; ``t_begin``: ``time.perf_counter()``
    at the start)."""
    steps = np.hypot(np.diff(meta.x), np.diff(meta.y))
    return {
        "image_dir": str(image_dir),
        "out": str(out),
        "frames": len(tags),
        "frames_found": len(files),
        "frames_dropped": sz.dropped,
        "frames_resized": len(sz.resize),
        "width": sz.width,
        "height": sz.height,
        "time_source": time_source,
        "time_ties_spread": ties,
        "heading_from": meta.heading_mode,
        "yaw_sources": dict(meta.yaw_sources),
        "height_sources": dict(hts.sources),
        "height_assumption": hts.assumption,
        "attitude_sources": dict(attitude_sources),
        "focal_mm": meta.focal,
        "focal_source": meta.focal_source,
        "sensor_width_mm": meta.sensor_w,
        "sensor_width_source": meta.sensor_source,
        "fx": fx,
        "height_m": camera.height_m,
        "height_min_m": float(hts.heights.min()),
        "height_max_m": float(hts.heights.max()),
        "ground_pixel_size_m": camera.height_m / fx,
        "origin_latitude": float(meta.lat[0]),
        "origin_longitude": float(meta.lon[0]),
        "extent_m": [float(meta.x.max() - meta.x.min()), float(meta.y.max() - meta.y.min())],
        "path_length_m": float(steps.sum()),
        "seconds": time.perf_counter() - t_begin,
    }


def import_geotagged(
    image_dir: str | Path,
    out: str | Path,
    *,
    focal_mm: float | None = None,
    sensor_width_mm: float | None = None,
    height_m: float | None = None,
    heading_deg: float | None = None,
    heading_from: str = "metadata",
    max_width: int | None = None,
    quiet: bool = True,
) -> dict:
    """Import the geotagged JPEGs of ``image_dir`` as a new drive log ``out``; returns the summary.

    ``focal_mm``, ``sensor_width_mm`` (mm) override the EXIF values; ``height_m`` (metres
    above ground) is the fallback for frames without their own height; ``heading_deg``
    (compass degrees clockwise from north) overrides every frame's heading, and
    ``heading_from="track"`` derives every frame's heading from the GPS track instead.

    Raises :class:`BadInput` on bad input (all missing metadata in one message); nothing
    is left under ``out`` then.
    """
    t_begin = time.perf_counter()
    image_dir, out = Path(image_dir), Path(out)
    _check_options(focal_mm, sensor_width_mm, height_m, heading_deg, heading_from, max_width)
    if not image_dir.is_dir():
        raise BadInput(image_dir, "image folder not found")
    replace = check_out_dir(out)
    files = _image_files(image_dir)
    tags = [read_geotag(p) for p in progress(files, label="read geotags", unit="images", quiet=quiet)]
    sz = _one_size(tags, max_width, image_dir)
    tags, frame_t, time_source, ties, time_origin = order_frames(sz.kept)
    meta = _metadata(tags, image_dir, focal_mm=focal_mm, sensor_width_mm=sensor_width_mm, height_m=height_m,
                     heading_deg=heading_deg, heading_from=heading_from)
    if ties:
        log.warning("%s: %d frames share a time stamp with another; spread within the stamp's resolution", image_dir, ties)
    fx = meta.focal / meta.sensor_w * sz.width
    hts = _heights(tags, height_m, image_dir)
    cx, cy = frame_centre((sz.height, sz.width))
    camera = CameraSpec(fx=fx, fy=fx, cx=cx, cy=cy, height_m=float(np.median(hts.heights)))
    odometry = np.column_stack([frame_t, meta.x, meta.y, theta_from_heading(meta.yaw)])
    images = _image_names(tags, sz.resize, image_dir)
    attitude_sources = Counter(g.attitude_source for g in tags if g.attitude_source)
    source = _source_table(image_dir, tags, files, sz, meta, hts, attitude_sources, time_source=time_source,
                           time_origin=time_origin, ties=ties, heading_deg=heading_deg)
    _write_log(out, replace, tags, images, sz, camera, frame_t, odometry, hts.heights, meta.yaw, source, quiet)
    return _summary(image_dir, out, files, tags, sz, meta, hts, camera, attitude_sources, fx=fx,
                    time_source=time_source, ties=ties, t_begin=t_begin)


def summary_line(s: dict) -> str:
    dropped = f", {len(s['frames_dropped'])} dropped" if s["frames_dropped"] else ""
    resized = f", {s['frames_resized']} resized" if s["frames_resized"] else ""
    return (
        f"import-geotagged: {s['frames']} of {s['frames_found']} frames{dropped}{resized}, "
        f"{s['width']} x {s['height']} px, height {s['height_m']:.1f} m (median), "
        f"~{s['ground_pixel_size_m']:.3f} m/px, extent {s['extent_m'][0]:.0f} x {s['extent_m'][1]:.0f} m, "
        f"times from {s['time_source']}, headings from {_counts_text(Counter(s['yaw_sources']))} -> {s['out']}"
    )
