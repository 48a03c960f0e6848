"""``mosaicmap import-bag``: turn a ROS 1 or ROS 2 bag into a drive log v1.

Reads one image topic and one odometry topic of a ROS 1 bag (a ``.bag`` file) or a ROS 2
bag (a directory with ``metadata.yaml`` and sqlite3 or mcap storage) with
:class:`rosbags.highlevel.AnyReader`, and writes a drive log directory (see
:mod:`pipeline.drivelog`) atomically: either the whole log appears under OUT, or nothing.

Images
    ``sensor_msgs/msg/Image`` with encoding ``mono8``, ``mono16``, ``rgb8``, ``bgr8``,
    ``rgba8`` or ``bgra8`` is written losslessly as an 8- or 16-bit PNG, grey or RGB (BGR
    is reordered to RGB; the alpha channel of rgba8/bgra8 is dropped, as readers would
    premultiply the colour by it; row padding (``step``) and ``is_bigendian`` are honoured).
    ``sensor_msgs/msg/CompressedImage`` whose ``format`` names ``jpeg``/``jpg`` or ``png``
    is written byte for byte (no recompression) as ``.jpg`` / ``.png``. Frames are named
    ``images/000000.png`` (or ``.jpg``) in message order.

Time stamps
    ``header.stamp`` (``sec`` + ``nanosec``; rosbags presents ROS 1 ``Time`` the same way),
    converted to seconds as the correctly rounded float of the integer nanoseconds. Only
    when a header stamp is exactly zero (a driver that does not stamp) the bag's receive
    time of that message is used instead; such messages are counted in the summary, the
    report and ``drive.toml [source]``. Stamps are absolute (e.g. Unix time), not shifted.

Odometry
    ``nav_msgs/msg/Odometry``: ``t`` = header stamp, ``x, y`` = ``pose.pose.position``,
    ``theta`` = yaw of ``pose.pose.orientation``
    (``atan2(2(wz + xy), w^2 + x^2 - y^2 - z^2)``, which equals
    ``atan2(2(wz + xy), 1 - 2(y^2 + z^2))`` for a unit quaternion and does not need one),
    wrapped with :func:`mapstore.grid.wrap_angle`.

Camera calibration
    ``--camera FILE``: a TOML file with a ``[camera]`` table exactly as in drive.toml (an
    existing drive.toml works too; other tables are ignored), validated by drivelog's own
    rules. A ``flat_field`` image named there (relative to FILE) is copied into the log
    under the same relative path. ``--pixel-size M``: the images are already rectified
    ground images of M metres per pixel. Exactly one of the two.

Validation (exit code 2, one line naming the bag and topic)
    bag missing or unreadable; topic not in the bag (the available topics are listed);
    topic of the wrong message type; no messages; an image encoding or compressed format
    not listed above; image header stamps decreasing or duplicate (likewise odometry
    stamps, which the drive log requires strictly increasing); fewer than two odometry
    samples; NaN/infinite odometry; frames outside the odometry time span (plus the
    ``[ingest] odometry_time_tolerance_s`` of the configuration, the same tolerance
    ingest applies).

Report keys (``--report FILE``): ``bag``, ``bag_format`` ("ros1" | "ros2"), ``out``,
``image_topic``, ``odom_topic``, ``frames``, ``frames_raw``, ``frames_compressed``,
``odometry_samples``, ``t_start``, ``t_end``, ``duration_s``,
``frames_stamped_from_receive_time``, ``odometry_stamped_from_receive_time``, ``seconds``.
"""

from __future__ import annotations

import logging
import math
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapstore.grid import wrap_angle
from pipeline.config import read_toml
from pipeline.drivelog import CameraSpec, parse_camera, read_drive_log, write_drive_log
from pipeline.errors import BadInput, JobFailed
from pipeline.fsutil import atomic_dir
from pipeline.images import write_image
from pipeline.progress import progress

log = logging.getLogger(__name__)

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)

# encoding -> (channels, numpy dtype of one sample, channels to keep, in RGB order). Alpha is
# dropped: cameras fill it with a constant, and OpenImageIO readers premultiply the colour
# by an alpha channel (a PNG stores it unassociated), which would alter the grey levels.
RAW_ENCODINGS: dict[str, tuple[int, str, tuple[int, ...] | None]] = {
    "mono8": (1, "u1", None),
    "mono16": (1, "u2", None),
    "rgb8": (3, "u1", None),
    "bgr8": (3, "u1", (2, 1, 0)),
    "rgba8": (4, "u1", (0, 1, 2)),
    "bgra8": (4, "u1", (2, 1, 0)),
}

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"


# --- pure helpers ------------------------------------------------------------------------


def stamp_ns(stamp: object) -> int:
    """Integer nanoseconds of a ROS ``Time`` (``sec``, ``nanosec``) as rosbags presents it."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_seconds(ns: int) -> float:
    """Seconds as the correctly rounded float of integer nanoseconds."""
    return ns / 1_000_000_000


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Heading (rotation about +z, radians, counter-clockwise) of a quaternion, wrapped.

    ``atan2(2(wz + xy), w^2 + x^2 - y^2 - z^2)``: for a unit quaternion this is the usual
    ``atan2(2(wz + xy), 1 - 2(y^2 + z^2))``; the homogeneous form needs no normalization.
    """
    return float(wrap_angle(math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)))


def odometry_pose(msg: object) -> tuple[float, float, float]:
    """``(x, y, theta)`` of a ``nav_msgs/Odometry`` message (position and wrapped yaw).

    Raises:
        ValueError: a position or orientation component is NaN or infinite, or the
            orientation is a zero quaternion.
    """
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    vals = {"position.x": p.x, "position.y": p.y, "orientation.x": q.x, "orientation.y": q.y,
            "orientation.z": q.z, "orientation.w": q.w}
    bad = [k for k, v in vals.items() if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{', '.join(bad)} not finite ({vals[bad[0]]})")
    if q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w < 1e-12:
        raise ValueError("orientation is a zero quaternion")
    return float(p.x), float(p.y), yaw_from_quaternion(q.x, q.y, q.z, q.w)


def decode_raw_image(
    height: int, width: int, encoding: str, is_bigendian: int, step: int, data: np.ndarray
) -> np.ndarray:
    """Pixels of a ``sensor_msgs/Image`` as ``(H, W)`` or ``(H, W, 3)`` uint8/uint16 (RGB order).

    Raises:
        ValueError: unsupported encoding or inconsistent size fields (message says which).
    """
    if encoding not in RAW_ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r} (supported: {', '.join(RAW_ENCODINGS)})")
    channels, sample, order = RAW_ENCODINGS[encoding]
    if height <= 0 or width <= 0:
        raise ValueError(f"empty image ({width} x {height})")
    itemsize = np.dtype(sample).itemsize
    row_bytes = width * channels * itemsize
    if step < row_bytes:
        raise ValueError(f"step {step} is less than width x bytes per pixel = {row_bytes}")
    buf = np.frombuffer(np.asarray(data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    need = step * (height - 1) + row_bytes
    if buf.size < need:
        raise ValueError(f"data has {buf.size} bytes, {width} x {height} {encoding} with step {step} needs {need}")
    if buf.size < step * height:  # last row without padding
        buf = np.concatenate([buf, np.zeros(step * height - buf.size, np.uint8)])
    rows = buf[: step * height].reshape(height, step)[:, :row_bytes]
    dtype = np.dtype(sample).newbyteorder(">" if is_bigendian else "<") if itemsize > 1 else np.dtype(sample)
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)
    # a native-order copy with the plain dtype (OpenImageIO refuses an explicit '<u2')
    pixels = pixels.astype(np.uint16 if itemsize > 1 else np.uint8)
    if order is not None:
        pixels = pixels[..., list(order)]
    if channels == 1:
        pixels = pixels[..., 0]
    return np.ascontiguousarray(pixels)


def compressed_extension(fmt: str, data: bytes) -> str:
    """``.png`` or ``.jpg`` for a ``CompressedImage`` of ``format`` ``fmt`` with these bytes.

    Raises:
        ValueError: unsupported format, or bytes that are not what the format says.
    """
    f = fmt.lower()
    if "compresseddepth" in f:
        raise ValueError(f"unsupported compressed format {fmt!r} (compressedDepth has a private header)")
    if "png" in f:
        ext, magic = ".png", PNG_MAGIC
    elif "jpeg" in f or "jpg" in f:
        ext, magic = ".jpg", JPEG_MAGIC
    else:
        raise ValueError(f"unsupported compressed format {fmt!r} (supported: formats naming jpeg or png)")
    if not data.startswith(magic):
        raise ValueError(f"format {fmt!r} but the data does not start with a {ext[1:].upper()} signature")
    return ext


def read_camera_toml(path: str | Path) -> CameraSpec:
    """The ``[camera]`` table of a TOML file, validated exactly as drive.toml's.

    Raises:
        BadInput: file missing, not TOML, or a calibration field missing or wrong.
    """
    path = Path(path)
    doc = read_toml(path, missing="camera file not found")
    # drivelog's own validation (the one read_drive_log applies), so the rules cannot drift.
    return parse_camera(path, doc.get("camera"))


def camera_from_options(camera_file: Path | None, pixel_size: float | None) -> CameraSpec:
    """The calibration from ``--camera FILE`` or ``--pixel-size M`` (exactly one)."""
    if (camera_file is None) == (pixel_size is None):
        raise BadInput("import-bag", "give exactly one of --camera FILE or --pixel-size M")
    if camera_file is not None:
        return read_camera_toml(camera_file)
    if not math.isfinite(pixel_size) or pixel_size <= 0:
        raise BadInput("--pixel-size", f"must be a positive number of metres, got {pixel_size}")
    return CameraSpec(pixel_size_m=float(pixel_size))


# --- import ------------------------------------------------------------------------------


@dataclass
class _Stamps:
    """Strictly increasing stamps of one topic, checked as they arrive."""

    where: str
    kind: str
    values: list[float] = field(default_factory=list)
    from_receive_time: int = 0

    def add(self, header_ns: int, receive_ns: int) -> float:
        i = len(self.values)
        if header_ns == 0:
            self.from_receive_time += 1
            header_ns = receive_ns
        t = ns_to_seconds(header_ns)
        if self.values:
            prev = self.values[-1]
            if t == prev:
                raise BadInput(self.where, f"{self.kind} message {i} has the same time stamp {t!r} as message {i - 1}")
            if t < prev:
                raise BadInput(
                    self.where,
                    f"{self.kind} message {i} has time stamp {t!r}, before message {i - 1}'s {prev!r} "
                    "(stamps must increase)",
                )
        self.values.append(t)
        return t


def _open_reader(bag: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not bag.exists():
        raise BadInput(bag, "bag not found")
    if bag.is_dir() and not (bag / "metadata.yaml").is_file():
        raise BadInput(bag, "not a ROS 2 bag directory (no metadata.yaml) and not a ROS 1 .bag file")
    # Bags normally carry their message definitions; the Humble store is only the fallback
    # for (old ROS 2) bags that do not.
    return AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _bag_errors() -> tuple[type[BaseException], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.serde import SerdeError

    return (AnyReaderError, ReaderError1, ReaderError2, SerdeError)


def _check_topic(bag: Path, topics: dict, topic: str, expected: tuple[str, ...], role: str):
    if topic not in topics:
        avail = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"
        raise BadInput(bag, f"{role} topic {topic!r} is not in the bag (available: {avail})")
    info = topics[topic]
    if info.msgtype not in expected:
        got = info.msgtype or "mixed message types"
        raise BadInput(f"{bag} topic {topic}", f"is {got}, the {role} topic must be {' or '.join(expected)}")
    if info.msgcount == 0:
        raise BadInput(f"{bag} topic {topic}", "has no messages")
    return info


@dataclass
class _Messages:
    """What the two topics held: image times and file names (relative to the log), odometry
    rows ``(t, x, y, theta)`` (seconds, metres, radians), and the image counts per kind."""

    frames: _Stamps
    odo_t: _Stamps
    images: list[str] = field(default_factory=list)
    odometry: list[tuple[float, float, float, float]] = field(default_factory=list)
    n_raw: int = 0
    n_compressed: int = 0


def _check_out(image_topic: str, odom_topic: str, out: Path) -> bool:
    """Check the topics differ and ``out`` is free; True when ``out`` is an empty directory
    (to be swapped for the finished log)."""
    if image_topic == odom_topic:
        raise BadInput("--image-topic/--odom-topic", f"both name the same topic {image_topic!r}")
    replace = False
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise BadInput(out, "exists and is not a directory")
        if any(out.iterdir()):
            raise BadInput(out, "output directory exists and is not empty (refusing to overwrite)")
        replace = True  # an empty directory: swap it for the finished log
    return replace


def _flat_field_source(camera: CameraSpec, camera_file: Path | None) -> Path | None:
    """The camera's ``flat_field`` image to copy into the log (relative to the camera file), or None."""
    if camera.flat_field is None:
        return None
    ff = Path(camera.flat_field)
    if camera_file is None or ff.is_absolute() or ".." in ff.parts:
        raise BadInput(
            f"{camera_file}[camera.flat_field]",
            f"{camera.flat_field!r} must be a path relative to the camera file, inside its folder",
        )
    return camera_file.parent / ff


def _open_bag(bag: Path, errors: tuple[type[BaseException], ...]):
    """The opened reader of ``bag`` (BadInput when it cannot be read)."""
    try:
        reader = _open_reader(bag)
        reader.open()
    except errors as e:
        raise BadInput(bag, f"cannot read bag: {_one_line(e)}") from None
    except (OSError, ValueError) as e:
        raise BadInput(bag, f"cannot read bag: {_one_line(e)}") from None
    return reader


def _write_image_message(tmp: Path, msg: object, msgtype: str, i: int, t: float, img_where: str,
                         got: _Messages) -> str:
    """Write image message ``i`` (time ``t``) under ``tmp/images``; returns its name in the log."""
    if msgtype == COMPRESSED_TYPE:
        data = np.asarray(msg.data, dtype=np.uint8).tobytes()
        try:
            ext = compressed_extension(msg.format, data)
        except ValueError as e:
            raise BadInput(img_where, f"image message {i} (t={t!r}): {e}") from None
        name = f"images/{i:06d}{ext}"
        (tmp / name).write_bytes(data)
        got.n_compressed += 1
    else:
        try:
            pixels = decode_raw_image(
                msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step, msg.data
            )
        except ValueError as e:
            raise BadInput(img_where, f"image message {i} (t={t!r}): {e}") from None
        name = f"images/{i:06d}.png"
        write_image(tmp / name, pixels)
        got.n_raw += 1
    return name


def _read_messages(reader, bag: Path, tmp: Path, errors: tuple[type[BaseException], ...], *, image_topic: str,
                   img_where: str, odo_where: str, wanted: list, total: int, quiet: bool) -> _Messages:
    """Read the two topics' messages in bag order: images written under ``tmp/images``,
    stamps and odometry checked as they arrive."""
    got = _Messages(_Stamps(img_where, "image"), _Stamps(odo_where, "odometry"))
    try:
        for conn, recv_ns, raw in progress(
            reader.messages(connections=wanted), length=total, label="import-bag", quiet=quiet
        ):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == image_topic:
                i = len(got.images)
                t = got.frames.add(stamp_ns(msg.header.stamp), recv_ns)
                got.images.append(_write_image_message(tmp, msg, conn.msgtype, i, t, img_where, got))
            else:
                try:
                    x, y, theta = odometry_pose(msg)
                except ValueError as e:
                    raise BadInput(odo_where, f"odometry message {len(got.odometry)}: {e}") from None
                t = got.odo_t.add(stamp_ns(msg.header.stamp), recv_ns)
                got.odometry.append((t, x, y, theta))
    except errors as e:
        raise BadInput(bag, f"cannot read bag: {_one_line(e)}") from None
    return got


def _check_time_span(got: _Messages, img_where: str, odo_where: str, time_tolerance_s: float) -> tuple[float, float]:
    """Check there are images, two odometry samples, and every image inside the odometry's
    time span (plus the tolerance, seconds); returns the span ``(t0, t1)``."""
    if not got.images:
        raise BadInput(img_where, "has no messages")
    if len(got.odometry) < 2:
        raise BadInput(odo_where, f"has {len(got.odometry)} odometry messages, need at least 2")
    t0, t1 = got.odometry[0][0], got.odometry[-1][0]
    for i, t in enumerate(got.frames.values):
        if t < t0 - time_tolerance_s or t > t1 + time_tolerance_s:
            raise BadInput(
                img_where,
                f"image message {i} at t={t!r} is outside the odometry time span "
                f"[{t0!r}, {t1!r}] (tolerance {time_tolerance_s} s, [ingest] odometry_time_tolerance_s)",
            )
    return t0, t1


def _copy_flat_field(flat_src: Path | None, tmp: Path, camera: CameraSpec) -> None:
    """Copy the camera's flat-field image into the log under its relative path (when it has one)."""
    if flat_src is not None:
        dst = tmp / camera.flat_field
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(flat_src, dst)


def _source_table(bag: Path, bag_format: str, image_topic: str, image_type: str, odom_topic: str,
                  got: _Messages) -> dict:
    """drive.toml's ``[source]`` table."""
    return {
        "kind": "rosbag",
        "bag": str(bag.resolve()),
        "bag_format": bag_format,
        "image_topic": image_topic,
        "image_type": image_type,
        "odom_topic": odom_topic,
        "frames_stamped_from_receive_time": got.frames.from_receive_time,
        "odometry_stamped_from_receive_time": got.odo_t.from_receive_time,
    }


def _write_log(tmp: Path, out: Path, camera: CameraSpec, got: _Messages, source: dict) -> None:
    """drive.toml, frames.csv and odometry.csv into ``tmp``, then read back with drivelog's rules."""
    write_drive_log(
        tmp, camera, np.asarray(got.frames.values), got.images, np.asarray(got.odometry), extra={"source": source}
    )
    try:
        read_drive_log(tmp)
    except BadInput as e:
        raise JobFailed(f"{out}: the written drive log does not validate: {e}") from None


def import_bag(
    bag: str | Path,
    out: str | Path,
    *,
    image_topic: str,
    odom_topic: str,
    camera: CameraSpec,
    camera_file: Path | None = None,
    time_tolerance_s: float = 0.0,
    quiet: bool = True,
) -> dict:
    """Import ``image_topic`` and ``odom_topic`` of ``bag`` into a new drive log ``out``.

    ``camera_file`` is where ``camera`` came from (to copy its ``flat_field`` image).
    Returns the summary (the report's keys). Raises :class:`BadInput` on bad input; nothing
    is left under ``out`` then.
    """
    t_begin = time.perf_counter()
    bag, out = Path(bag), Path(out)
    replace = _check_out(image_topic, odom_topic, out)
    flat_src = _flat_field_source(camera, camera_file)
    errors = _bag_errors()
    reader = _open_bag(bag, errors)
    try:
        bag_format = "ros2" if reader.is2 else "ros1"
        topics = reader.topics
        img_info = _check_topic(bag, topics, image_topic, IMAGE_TYPES, "image")
        _check_topic(bag, topics, odom_topic, (ODOMETRY_TYPE,), "odometry")
        img_where = f"{bag} topic {image_topic}"
        odo_where = f"{bag} topic {odom_topic}"
        wanted = [c for c in reader.connections if c.topic in (image_topic, odom_topic)]
        total = topics[image_topic].msgcount + topics[odom_topic].msgcount
        with atomic_dir(out, replace=replace) as tmp:
            (tmp / "images").mkdir()
            got = _read_messages(reader, bag, tmp, errors, image_topic=image_topic, img_where=img_where,
                                 odo_where=odo_where, wanted=wanted, total=total, quiet=quiet)
            t0, t1 = _check_time_span(got, img_where, odo_where, time_tolerance_s)
            _copy_flat_field(flat_src, tmp, camera)
            source = _source_table(bag, bag_format, image_topic, img_info.msgtype, odom_topic, got)
            _write_log(tmp, out, camera, got, source)
    finally:
        reader.close()

    for kind, n in (("image", got.frames.from_receive_time), ("odometry", got.odo_t.from_receive_time)):
        if n:
            log.warning("%s: %d %s messages had a zero header stamp; their bag receive time was used", bag, n, kind)
    return _summary(bag, out, bag_format, image_topic, odom_topic, got, t0, t1, t_begin)


def _summary(bag: Path, out: Path, bag_format: str, image_topic: str, odom_topic: str, got: _Messages,
             t0: float, t1: float, t_begin: float) -> dict:
    """The report (see the module docstring); ``t0, t1``: the odometry's time span (seconds),
    ``t_begin``: ``time.perf_counter()`` at the import's start."""
    t_start = min(got.frames.values[0], t0)
    t_end = max(got.frames.values[-1], t1)
    return {
        "bag": str(bag),
        "bag_format": bag_format,
        "out": str(out),
        "image_topic": image_topic,
        "odom_topic": odom_topic,
        "frames": len(got.images),
        "frames_raw": got.n_raw,
        "frames_compressed": got.n_compressed,
        "odometry_samples": len(got.odometry),
        "t_start": t_start,
        "t_end": t_end,
        "duration_s": t_end - t_start,
        "frames_stamped_from_receive_time": got.frames.from_receive_time,
        "odometry_stamped_from_receive_time": got.odo_t.from_receive_time,
        "seconds": time.perf_counter() - t_begin,
    }


def _one_line(e: BaseException) -> str:
    text = " ".join(str(x) for x in e.args) if e.args else type(e).__name__
    return " ".join(text.split()) or type(e).__name__


def summary_line(s: dict) -> str:
    return (
        f"import-bag: {s['frames']} frames ({s['frames_raw']} raw, {s['frames_compressed']} compressed), "
        f"{s['odometry_samples']} odometry samples, t {s['t_start']:.3f} .. {s['t_end']:.3f} "
        f"({s['duration_s']:.3f} s) -> {s['out']}"
    )
