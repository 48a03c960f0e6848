"""`mosaicmap import-bag`: ROS 1 / ROS 2 bags written here with rosbags -> drive log v1."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest
from click.testing import CliRunner
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from mapstore.grid import wrap_angle
from pipeline.importers.bag import compressed_extension, decode_raw_image, yaw_from_quaternion
from pipeline.drivelog import read_drive_log

BASE_SEC = 1_700_000_000
N_ODOM = 20
ODOM_DT_NS = 100_000_000  # 0.1 s
RNG = np.random.default_rng(7)


# --- building bags -----------------------------------------------------------------------


def _stamp(ns: int) -> tuple[int, int]:
    return ns // 1_000_000_000, ns % 1_000_000_000


def raw_frames() -> list[dict]:
    """Raw Image frames: (encoding, pixels as they should decode, wire bytes, step, bigendian)."""
    h, w = 24, 32
    out = []
    m8 = RNG.integers(0, 256, (h, w), dtype=np.uint8)
    out.append(dict(encoding="mono8", expect=m8, step=w, data=m8.tobytes(), be=0))
    m8p = RNG.integers(0, 256, (h, w), dtype=np.uint8)  # rows padded to step 40
    padded = np.zeros((h, 40), np.uint8)
    padded[:, :w] = m8p
    out.append(dict(encoding="mono8", expect=m8p, step=40, data=padded.tobytes(), be=0))
    rgb = RNG.integers(0, 256, (h, w, 3), dtype=np.uint8)
    out.append(dict(encoding="rgb8", expect=rgb, step=3 * w, data=rgb.tobytes(), be=0))
    bgra = RNG.integers(0, 256, (h, w, 4), dtype=np.uint8)  # wire order B, G, R, A; alpha is dropped
    out.append(dict(encoding="bgra8", expect=bgra[..., [2, 1, 0]], step=4 * w, data=bgra.tobytes(), be=0))
    m16 = RNG.integers(0, 65536, (h, w), dtype=np.uint16)
    out.append(dict(encoding="mono16", expect=m16, step=2 * w, data=m16.astype("<u2").tobytes(), be=0))
    m16b = RNG.integers(0, 65536, (h, w), dtype=np.uint16)
    out.append(dict(encoding="mono16", expect=m16b, step=2 * w, data=m16b.astype(">u2").tobytes(), be=1))
    return out


def compressed_frames() -> list[dict]:
    grey = RNG.integers(0, 256, (20, 30), dtype=np.uint8)
    colour = RNG.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", grey)
    ok2, jpg = cv2.imencode(".jpg", colour)
    assert ok and ok2
    return [
        dict(format="png", data=png.tobytes(), ext=".png", expect=grey),
        dict(format="rgb8; jpeg compressed bgr8", data=jpg.tobytes(), ext=".jpg", expect=None),
        dict(format="mono8; png compressed", data=png.tobytes(), ext=".png", expect=grey),
    ]


def frame_ns(i: int) -> int:
    return (BASE_SEC * 1_000_000_000) + 250_000_123 + i * 300_000_017


def odom_ns(k: int) -> int:
    return (BASE_SEC * 1_000_000_000) + k * ODOM_DT_NS


def odom_pose(k: int) -> tuple[float, float, float]:
    return 0.1 * k - 0.5, 0.03 * k * k, -3.0 + 0.35 * k  # yaw runs past +pi: tests wrapping


class BagBuilder:
    """Writes a ROS 1 or ROS 2 bag with whatever topics a test asks for."""

    def __init__(self, path: Path, ros: int, storage: StoragePlugin = StoragePlugin.SQLITE3):
        self.ros = ros
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
        self.writer = Writer1(path) if ros == 1 else Writer2(path, version=9, storage_plugin=storage)
        self.conns: dict[str, object] = {}
        self.path = path

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()
        return False

    def header(self, ns: int):
        T = self.ts.types
        sec, nsec = _stamp(ns)
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if self.ros == 1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="base")
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id="base")

    def write(self, topic: str, msg, recv_ns: int) -> None:
        typ = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, typ, typestore=self.ts)
        data = self.ts.serialize_ros1(msg, typ) if self.ros == 1 else self.ts.serialize_cdr(msg, typ)
        self.writer.write(self.conns[topic], recv_ns, data)

    def image(self, topic: str, ns: int, f: dict, *, recv_ns: int | None = None) -> None:
        h, w = f["expect"].shape[:2]
        msg = self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(ns), height=h, width=w, encoding=f["encoding"], is_bigendian=f["be"],
            step=f["step"], data=np.frombuffer(f["data"], np.uint8).copy(),
        )
        self.write(topic, msg, ns if recv_ns is None else recv_ns)

    def compressed(self, topic: str, ns: int, f: dict) -> None:
        msg = self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(ns), format=f["format"], data=np.frombuffer(f["data"], np.uint8).copy()
        )
        self.write(topic, msg, ns)

    def odom(self, topic: str, ns: int, x: float, y: float, yaw: float, *, recv_ns: int | None = None) -> None:
        T = self.ts.types
        cov = np.zeros(36, np.float64)
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
            ),
            covariance=cov,
        )
        zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov
        )
        msg = T["nav_msgs/msg/Odometry"](header=self.header(ns), child_frame_id="base_link", pose=pose, twist=twist)
        self.write(topic, msg, ns if recv_ns is None else recv_ns)

    def standard_odometry(self, topic: str = "/odom") -> None:
        for k in range(N_ODOM):
            self.odom(topic, odom_ns(k), *odom_pose(k))


def build_standard_bag(path: Path, ros: int, storage: StoragePlugin = StoragePlugin.SQLITE3):
    raws, comps = raw_frames(), compressed_frames()
    with BagBuilder(path, ros, storage) as b:
        b.standard_odometry()
        for i, f in enumerate(raws):
            b.image("/cam/image_raw", frame_ns(i), f)
        for i, f in enumerate(comps):
            b.compressed("/cam/image_raw/compressed", frame_ns(i), f)
    return raws, comps


def run(*args: str):
    from pipeline.cli import cli

    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def read_native(path: Path) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    px = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
    inp.close()
    px = np.asarray(px).reshape(spec.height, spec.width, spec.nchannels)
    return px[..., 0] if spec.nchannels == 1 else px


def check_odometry(log) -> None:
    assert log.odometry.shape == (N_ODOM, 4)
    for k in range(N_ODOM):
        t, x, y, th = log.odometry[k]
        ex, ey, eyaw = odom_pose(k)
        assert t == odom_ns(k) / 10**9
        assert (x, y) == (ex, ey)
        assert th == pytest.approx(float(wrap_angle(eyaw)), abs=1e-12)
        assert -math.pi <= th < math.pi


# --- round trips -------------------------------------------------------------------------


@pytest.mark.parametrize("ros,storage", [(1, None), (2, StoragePlugin.SQLITE3), (2, StoragePlugin.MCAP)])
def test_round_trip_raw_images(tmp_path, ros, storage):
    bag = tmp_path / ("in.bag" if ros == 1 else "in_bag")
    raws, _ = build_standard_bag(bag, ros, storage or StoragePlugin.SQLITE3)
    out = tmp_path / "log"
    res = run("import-bag", bag, out, "--image-topic", "/cam/image_raw", "--odom-topic", "/odom",
              "--pixel-size", "0.0025", "--quiet")
    assert res.exit_code == 0, res.output
    assert "6 frames" in res.output and "20 odometry samples" in res.output

    log = read_drive_log(out)
    assert log.camera.pixel_size_m == 0.0025
    assert log.frame_t.tolist() == [frame_ns(i) / 10**9 for i in range(len(raws))]
    assert log.frame_images == [f"images/{i:06d}.png" for i in range(len(raws))]
    for i, f in enumerate(raws):
        got = read_native(log.image_path(i))
        assert got.dtype == f["expect"].dtype
        np.testing.assert_array_equal(got, f["expect"])
    check_odometry(log)
    assert log.meta["source"]["bag_format"] == f"ros{ros}"
    assert log.meta["source"]["frames_stamped_from_receive_time"] == 0
    assert not any(p.name.startswith(".tmp-") for p in tmp_path.iterdir())


@pytest.mark.parametrize("ros", [1, 2])
def test_round_trip_compressed_images_byte_for_byte(tmp_path, ros):
    bag = tmp_path / ("in.bag" if ros == 1 else "in_bag")
    _, comps = build_standard_bag(bag, ros)
    out = tmp_path / "log"
    report = tmp_path / "report.json"
    res = run("import-bag", bag, out, "--image-topic", "/cam/image_raw/compressed", "--odom-topic", "/odom",
              "--pixel-size", "0.002", "--report", report, "--quiet")
    assert res.exit_code == 0, res.output
    log = read_drive_log(out)
    assert log.frame_images == [f"images/{i:06d}{f['ext']}" for i, f in enumerate(comps)]
    for i, f in enumerate(comps):
        assert log.image_path(i).read_bytes() == f["data"]
        if f["expect"] is not None:
            np.testing.assert_array_equal(read_native(log.image_path(i)), f["expect"])
    import json

    rep = json.loads(report.read_text())
    assert rep["frames"] == 3 and rep["frames_compressed"] == 3 and rep["odometry_samples"] == N_ODOM


def test_camera_file_and_flat_field(tmp_path):
    bag = tmp_path / "in.bag"
    build_standard_bag(bag, 1)
    calib = tmp_path / "calib"
    calib.mkdir()
    (calib / "ff.png").write_bytes(cv2.imencode(".png", np.full((24, 32), 200, np.uint8))[1].tobytes())
    cam = calib / "camera.toml"
    cam.write_text(
        "[camera]\nmodel = \"downward\"\nfx = 400.0\nfy = 401.0\ncx = 15.5\ncy = 11.5\nheight_m = 0.3\n"
        "k1 = -0.1\nflat_field = \"ff.png\"\n"
    )
    out = tmp_path / "log"
    res = run("import-bag", bag, out, "--image-topic", "/cam/image_raw", "--odom-topic", "/odom", "--camera", cam)
    assert res.exit_code == 0, res.output
    log = read_drive_log(out)
    assert (log.camera.fx, log.camera.fy, log.camera.height_m, log.camera.k1) == (400.0, 401.0, 0.3, -0.1)
    assert (out / "ff.png").read_bytes() == (calib / "ff.png").read_bytes()


def test_zero_header_stamp_falls_back_to_receive_time(tmp_path):
    bag = tmp_path / "in.bag"
    f = raw_frames()[0]
    with BagBuilder(bag, 1) as b:
        b.standard_odometry()
        b.image("/cam", frame_ns(0), f)
        b.image("/cam", 0, f, recv_ns=frame_ns(1))  # unstamped driver
    out = tmp_path / "log"
    res = run("import-bag", bag, out, "--image-topic", "/cam", "--odom-topic", "/odom", "--pixel-size", "0.001")
    assert res.exit_code == 0, res.output
    log = read_drive_log(out)
    assert log.frame_t.tolist() == [frame_ns(0) / 10**9, frame_ns(1) / 10**9]
    assert log.meta["source"]["frames_stamped_from_receive_time"] == 1


# --- bad input ---------------------------------------------------------------------------


def _err(res) -> str:
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    return lines[0]


@pytest.fixture(scope="module")
def std_bag(tmp_path_factory) -> Path:
    bag = tmp_path_factory.mktemp("bags") / "std.bag"
    build_standard_bag(bag, 1)
    return bag


def test_missing_topic_lists_available(std_bag, tmp_path):
    out = tmp_path / "log"
    msg = _err(run("import-bag", std_bag, out, "--image-topic", "/nope", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "/nope" in msg and "/cam/image_raw" in msg and "/odom" in msg
    assert not out.exists()


def test_wrong_message_type(std_bag, tmp_path):
    msg = _err(run("import-bag", std_bag, tmp_path / "log", "--image-topic", "/odom", "--odom-topic", "/cam/image_raw",
                   "--pixel-size", "0.001"))
    assert "/odom" in msg and "nav_msgs/msg/Odometry" in msg


def test_wrong_encoding(tmp_path):
    bag = tmp_path / "in_bag"
    f = dict(raw_frames()[0], encoding="yuv422")
    with BagBuilder(bag, 2) as b:
        b.standard_odometry()
        b.image("/cam", frame_ns(0), f)
    out = tmp_path / "log"
    msg = _err(run("import-bag", bag, out, "--image-topic", "/cam", "--odom-topic", "/odom", "--pixel-size", "0.001"))
    assert "/cam" in msg and "yuv422" in msg
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["in_bag"]


def test_missing_bag(tmp_path):
    msg = _err(run("import-bag", tmp_path / "absent.bag", tmp_path / "log", "--image-topic", "/cam",
                   "--odom-topic", "/odom", "--pixel-size", "0.001"))
    assert "absent.bag" in msg and "not found" in msg


def test_unreadable_bag(tmp_path):
    bag = tmp_path / "junk.bag"
    bag.write_bytes(b"this is not a bag")
    msg = _err(run("import-bag", bag, tmp_path / "log", "--image-topic", "/cam", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "junk.bag" in msg


@pytest.mark.parametrize("extra", [[], ["--pixel-size", "0.001", "--camera", "cam.toml"]])
def test_exactly_one_calibration(std_bag, tmp_path, extra):
    msg = _err(run("import-bag", std_bag, tmp_path / "log", "--image-topic", "/cam/image_raw", "--odom-topic", "/odom",
                   *extra))
    assert "--camera" in msg and "--pixel-size" in msg


def test_bad_camera_file(std_bag, tmp_path):
    cam = tmp_path / "cam.toml"
    cam.write_text('[camera]\nmodel = "downward"\nfx = 400.0\n')
    msg = _err(run("import-bag", std_bag, tmp_path / "log", "--image-topic", "/cam/image_raw", "--odom-topic", "/odom",
                   "--camera", cam))
    assert "cam.toml" in msg and "camera." in msg


def test_refuses_non_empty_out(std_bag, tmp_path):
    out = tmp_path / "log"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    msg = _err(run("import-bag", std_bag, out, "--image-topic", "/cam/image_raw", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "not empty" in msg
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_empty_out_dir_is_fine(std_bag, tmp_path):
    out = tmp_path / "log"
    out.mkdir()
    res = run("import-bag", std_bag, out, "--image-topic", "/cam/image_raw", "--odom-topic", "/odom",
              "--pixel-size", "0.001", "-q")
    assert res.exit_code == 0, res.output
    assert len(read_drive_log(out).frame_images) == 6


@pytest.mark.parametrize("second_ns,word", [(frame_ns(0), "same time stamp"), (frame_ns(0) - 1000, "before")])
def test_image_stamps_must_increase(tmp_path, second_ns, word):
    bag = tmp_path / "in.bag"
    f = raw_frames()[0]
    with BagBuilder(bag, 1) as b:
        b.standard_odometry()
        b.image("/cam", frame_ns(0), f)
        b.image("/cam", second_ns, f, recv_ns=frame_ns(1))
    msg = _err(run("import-bag", bag, tmp_path / "log", "--image-topic", "/cam", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "/cam" in msg and "message 1" in msg and word in msg


def test_odometry_nan(tmp_path):
    bag = tmp_path / "in.bag"
    with BagBuilder(bag, 1) as b:
        b.standard_odometry()
        b.odom("/odom", odom_ns(N_ODOM), float("nan"), 0.0, 0.0)
        b.image("/cam", frame_ns(0), raw_frames()[0])
    msg = _err(run("import-bag", bag, tmp_path / "log", "--image-topic", "/cam", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "/odom" in msg and f"message {N_ODOM}" in msg and "x" in msg


def test_frames_outside_odometry_span(tmp_path):
    bag = tmp_path / "in.bag"
    with BagBuilder(bag, 1) as b:
        b.standard_odometry()
        b.image("/cam", frame_ns(0), raw_frames()[0])
        b.image("/cam", odom_ns(N_ODOM + 5), raw_frames()[0])
    msg = _err(run("import-bag", bag, tmp_path / "log", "--image-topic", "/cam", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "/cam" in msg and "message 1" in msg and "outside the odometry time span" in msg


def test_unsupported_compressed_format(tmp_path):
    bag = tmp_path / "in.bag"
    with BagBuilder(bag, 1) as b:
        b.standard_odometry()
        b.compressed("/cam/c", frame_ns(0), dict(format="tiff", data=b"II*\x00rest"))
    msg = _err(run("import-bag", bag, tmp_path / "log", "--image-topic", "/cam/c", "--odom-topic", "/odom",
                   "--pixel-size", "0.001"))
    assert "/cam/c" in msg and "tiff" in msg


# --- pure helpers ------------------------------------------------------------------------


def test_yaw_from_quaternion():
    for yaw in np.linspace(-3.1, 3.1, 13):
        q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        assert yaw_from_quaternion(*q) == pytest.approx(yaw, abs=1e-12)
        assert yaw_from_quaternion(*(2.0 * v for v in q)) == pytest.approx(yaw, abs=1e-12)  # not normalized
    assert yaw_from_quaternion(0.0, 0.0, 1.0, 0.0) == -math.pi  # wrapped to [-pi, pi)


def test_decode_raw_image_errors():
    with pytest.raises(ValueError, match="encoding"):
        decode_raw_image(2, 2, "32FC1", 0, 8, np.zeros(16, np.uint8))
    with pytest.raises(ValueError, match="bytes"):
        decode_raw_image(2, 2, "mono8", 0, 2, np.zeros(3, np.uint8))
    with pytest.raises(ValueError, match="step"):
        decode_raw_image(2, 2, "rgb8", 0, 4, np.zeros(12, np.uint8))


def test_compressed_extension():
    assert compressed_extension("jpeg", b"\xff\xd8\xff\xe0") == ".jpg"
    assert compressed_extension("bgr8; png compressed", b"\x89PNG\r\n\x1a\nxx") == ".png"
    with pytest.raises(ValueError, match="signature"):
        compressed_extension("png", b"\xff\xd8\xff")
    with pytest.raises(ValueError, match="compressedDepth"):
        compressed_extension("16UC1; compressedDepth png", b"\x00" * 12 + b"\x89PNG\r\n\x1a\n")


def test_drive_toml_is_tomllib_readable(std_bag, tmp_path):
    out = tmp_path / "log"
    assert run("import-bag", std_bag, out, "--image-topic", "/cam/image_raw", "--odom-topic", "/odom",
               "--pixel-size", "0.001", "-q").exit_code == 0
    doc = tomllib.loads((out / "drive.toml").read_text())
    assert doc["format_version"] == 1 and doc["source"]["image_topic"] == "/cam/image_raw"


def test_decode_rgba_drops_alpha_and_honours_padding():
    px = RNG.integers(0, 256, (3, 5, 4), dtype=np.uint8)
    wire = np.zeros((3, 24), np.uint8)
    wire[:, :20] = px.reshape(3, 20)
    got = decode_raw_image(3, 5, "rgba8", 0, 24, wire.ravel()[:-4])  # last row unpadded
    np.testing.assert_array_equal(got, px[..., :3])
