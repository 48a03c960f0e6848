"""`mosaicmap import-tiles` and `mosaicmap import-geotagged`: synthetic inputs and the real sets."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest
from click.testing import CliRunner

from mapstore.grid import MapGrid, frame_pixels_to_world, wrap_angle
from pipeline.cli import cli
from pipeline.drivelog import read_drive_log, read_pose_csv
from pipeline.errors import BadInput
from pipeline.importers.geotagged import local_east_north, spread_ties, theta_from_heading, track_headings
from pipeline.importers.tiles import read_tile_configuration, tile_pose, tile_positions_from_poses

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
RNG = np.random.default_rng(11)


def run(*args) -> object:
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def one_error_line(res) -> str:
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    return lines[0]


def require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data {path} absent (../shared is not checked out beside the repository)")
    return path


# --- import-tiles: synthetic ---------------------------------------------------------------

TILE_W, TILE_H, STEP_X, STEP_Y = 24, 20, 18, 15
TILE_CONFIG = """# Define the number of dimensions we are working on
dim = 2

# Define the image coordinates
a.png; ; (0.0, 0.0)
b.png; ; ({sx}, 0.0)
d.png;;({sx}.0,{sy}.5)
c.png ; ; (0, {sy})
"""
TILE_POS = {"a.png": (0.0, 0.0), "b.png": (STEP_X, 0.0), "d.png": (STEP_X, STEP_Y + 0.5), "c.png": (0.0, STEP_Y)}
PEER_POS = {"a.png": (0.0, 0.0), "b.png": (STEP_X + 0.4, -0.2), "d.png": (STEP_X + 0.3, STEP_Y + 0.9), "c.png": (0.1, STEP_Y - 0.3)}


def make_tiles(d: Path, *, peer: bool = True) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    for name in TILE_POS:
        buf = oiio.ImageBuf(RNG.integers(0, 65536, (TILE_H, TILE_W), dtype=np.uint16))
        assert buf.write(str(d / name))
    (d / "TileConfiguration.txt").write_text(TILE_CONFIG.format(sx=STEP_X, sy=STEP_Y))
    if peer:
        lines = ["dim = 2"] + [f"{n}; ; ({x!r}, {y!r})" for n, (x, y) in PEER_POS.items()]
        (d / "TileConfiguration.registered.txt").write_text("\n".join(lines) + "\n")
    return d / "TileConfiguration.txt"


def test_read_tile_configuration(tmp_path):
    cfg = make_tiles(tmp_path / "src")
    assert read_tile_configuration(cfg) == [(n, float(x), float(y)) for n, (x, y) in TILE_POS.items()]


def test_tile_pose_follows_grid_conventions():
    shape, m = (TILE_H, TILE_W), 0.002
    pose = tile_pose(7.0, 3.0, shape, m)
    assert pose == pytest.approx([(7 + (TILE_W - 1) / 2) * m, -(3 + (TILE_H - 1) / 2) * m, 0.0])
    # tile pixel (c, r) lies where mosaic pixel (7 + c, 3 + r) does on the grid's north-up raster
    grid = MapGrid(0.0, 0.0, m, 100, 100)
    cols, rows = np.array([0.0, 5.0, TILE_W - 1]), np.array([0.0, 9.0, TILE_H - 1])
    wx, wy = frame_pixels_to_world(pose, cols, rows, shape, m)
    gx, gy = grid.pixel_to_world(7 + cols, 3 + rows)
    np.testing.assert_allclose(wx, gx, atol=1e-12)
    np.testing.assert_allclose(wy, gy, atol=1e-12)
    back = tile_positions_from_poses(pose[None], shape, m)
    np.testing.assert_allclose(back, [[7.0, 3.0]], atol=1e-9)


def test_import_tiles(tmp_path):
    cfg = make_tiles(tmp_path / "src")
    out = tmp_path / "log"
    m = 0.001
    res = run("import-tiles", cfg, out, "--pixel-size", m, "--peer", cfg.parent / "TileConfiguration.registered.txt",
              "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    assert "4 tiles" in res.output
    lg = read_drive_log(out)
    assert lg.camera.pixel_size_m == m
    np.testing.assert_array_equal(lg.frame_t, [0, 1, 2, 3])
    names = list(TILE_POS)
    assert lg.frame_images == [f"images/{n}" for n in names]
    for n in names:  # copied byte for byte
        assert (out / "images" / n).read_bytes() == (cfg.parent / n).read_bytes()
    np.testing.assert_array_equal(lg.odometry[:, 0], lg.frame_t)
    expect = np.array([[(x + (TILE_W - 1) / 2) * m, -(y + (TILE_H - 1) / 2) * m] for x, y in TILE_POS.values()])
    np.testing.assert_allclose(lg.odometry[:, 1:3], expect, atol=1e-12)
    assert np.all(lg.odometry[:, 3] == 0)
    np.testing.assert_allclose(tile_positions_from_poses(lg.odometry, (TILE_H, TILE_W), m), list(TILE_POS.values()), atol=1e-9)
    # the peer's answer: evaluation only, never an input of the build
    peer = read_pose_csv(out / "peer_positions.csv")
    np.testing.assert_allclose(tile_positions_from_poses(peer, (TILE_H, TILE_W), m), list(PEER_POS.values()), atol=1e-9)
    assert out / "peer_positions.csv" not in lg.files()
    assert lg.meta["source"]["peer_positions"] == "peer_positions.csv"


def test_import_tiles_malformed_line(tmp_path):
    cfg = make_tiles(tmp_path / "src", peer=False)
    text = cfg.read_text().splitlines()
    text[5] = "b.png; ; (18.0; 0.0)"  # line 6
    cfg.write_text("\n".join(text) + "\n")
    res = run("import-tiles", cfg, tmp_path / "log", "--pixel-size", "0.001")
    assert res.exit_code == 2
    line = one_error_line(res)
    assert f"{cfg}:6" in line and "malformed" in line
    assert not (tmp_path / "log").exists()
    with pytest.raises(BadInput, match=":6"):
        read_tile_configuration(cfg)


@pytest.mark.parametrize("defect, where", [
    ("missing", "TileConfiguration.txt:7"),      # d.png deleted
    ("size", "TileConfiguration.txt:7"),         # d.png of another size
    ("dim", "TileConfiguration.txt:2"),
    ("duplicate", "TileConfiguration.txt:8"),
])
def test_import_tiles_bad_input(tmp_path, defect, where):
    cfg = make_tiles(tmp_path / "src", peer=False)
    if defect == "missing":
        (cfg.parent / "d.png").unlink()
    elif defect == "size":
        assert oiio.ImageBuf(np.zeros((TILE_H + 1, TILE_W), np.uint8)).write(str(cfg.parent / "d.png"))
    elif defect == "dim":
        cfg.write_text(cfg.read_text().replace("dim = 2", "dim = 3"))
    else:
        cfg.write_text(cfg.read_text().replace("c.png ; ;", "a.png ; ;"))
    res = run("import-tiles", cfg, tmp_path / "log", "--pixel-size", "0.001")
    assert res.exit_code == 2, res.output
    assert where in one_error_line(res)
    assert not (tmp_path / "log").exists()


# --- import-geotagged: synthetic -----------------------------------------------------------

LAT0, LON0 = 41.0346708, -83.3057253


def degrees_to_dms(deg: float) -> tuple[float, float, float]:
    a = abs(deg)
    d = math.floor(a)
    mnt = math.floor((a - d) * 60)
    return float(d), float(mnt), (a - d - mnt / 60) * 3600


XMP_NAMESPACES = {"sensefly": "http://ns.sensefly.com/sensefly/1.0/", "drone-dji": "http://www.dji.com/drone-dji/1.0/"}


def inject_xmp(path: Path, fields: dict[str, object], ns: str = "sensefly") -> None:
    """Add an XMP packet as an APP1 segment right after the JPEG's SOI (OpenImageIO writes none).

    senseFly properties are written as elements, DJI's (``ns="drone-dji"``) as attributes of
    ``rdf:Description`` with signed text values, as DJI cameras write them.
    """
    if ns == "drone-dji":
        attrs = "".join(f' drone-dji:{k}="{v:+.2f}"' if isinstance(v, float) else f' drone-dji:{k}="{v}"'
                        for k, v in fields.items())
        desc = f"<rdf:Description rdf:about='DJI Meta Data' xmlns:drone-dji='{XMP_NAMESPACES[ns]}'{attrs}/>"
    else:
        body = "".join(f"<{ns}:{k}>{v}</{ns}:{k}>" for k, v in fields.items())
        desc = f"<rdf:Description rdf:about='' xmlns:{ns}='{XMP_NAMESPACES[ns]}'>{body}</rdf:Description>"
    packet = (
        "<?xpacket begin='\ufeff' id='W5M0MpCehiHzreSzNTczkc9d'?><x:xmpmeta xmlns:x='adobe:ns:meta/'>"
        f"<rdf:RDF xmlns:rdf='http://www.w3.org/1999/02/22-rdf-syntax-ns#'>{desc}"
        "</rdf:RDF></x:xmpmeta><?xpacket end='w'?>"
    ).encode()
    payload = b"http://ns.adobe.com/xap/1.0/\0" + packet
    data = path.read_bytes()
    assert data[:2] == b"\xff\xd8"
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:])


def write_geotagged(path: Path, *, east: float | None, north: float = 0.0, when: str = "2013:06:04 13:37:29",
                    size: tuple[int, int] = (64, 48), xmp: dict | None = None, xmp_ns: str = "sensefly",
                    focal: float | None = 4.3, focal_plane: bool = True, focal35: int | None = None) -> None:
    """A small JPEG at ``east``/``north`` metres from (LAT0, LON0) (no GPS when east is None).

    EXIF: the focal length (none when ``focal`` is None), a 6.2 mm wide sensor's focal
    plane resolution (unless ``focal_plane`` is False), the 35 mm equivalent ``focal35``.
    """
    w, h = size
    buf = oiio.ImageBuf(RNG.integers(0, 256, (h, w, 3), dtype=np.uint8))
    sp = buf.specmod()
    if east is not None:
        lat, lon = LAT0 + north / 111_030.0, LON0 + east / 84_000.0  # near; exact metres come from the importer's projection
        sp.attribute("GPS:Latitude", oiio.TypeDesc("float[3]"), degrees_to_dms(lat))
        sp.attribute("GPS:LatitudeRef", "N")
        sp.attribute("GPS:Longitude", oiio.TypeDesc("float[3]"), degrees_to_dms(lon))
        sp.attribute("GPS:LongitudeRef", "W")
        sp.attribute("GPS:Altitude", 281.5)
    sp.attribute("Exif:DateTimeOriginal", when)
    if focal is not None:
        sp.attribute("Exif:FocalLength", focal)
    if focal_plane:
        sp.attribute("Exif:PixelXDimension", 4000)
        sp.attribute("Exif:FocalPlaneXResolution", 4000 / 6.2 * 25.4)  # a 6.2 mm wide sensor
        sp.attribute("Exif:FocalPlaneResolutionUnit", 2)
    if focal35 is not None:
        sp.attribute("Exif:FocalLengthIn35mmFilm", int(focal35))  # written as EXIF SHORT
    assert buf.write(str(path)), buf.geterror()
    if xmp:
        inject_xmp(path, xmp, xmp_ns)


def geo_of(path: Path) -> tuple[float, float]:
    s = oiio.ImageInput.open(str(path)).spec()
    la, lo = s.getattribute("GPS:Latitude"), s.getattribute("GPS:Longitude")
    return la[0] + la[1] / 60 + la[2] / 3600, -(lo[0] + lo[1] / 60 + lo[2] / 3600)


# file name -> (east, north, time, heading, height)
GEO_FRAMES = {
    "IMG_0003.jpg": (40.0, 10.0, "2013:06:04 13:37:40", 80.0, 70.0),
    "IMG_0001.jpg": (0.0, 0.0, "2013:06:04 13:37:29", 70.0, 66.0),
    "IMG_0002.jpg": (20.0, 5.0, "2013:06:04 13:37:35", 75.0, 68.0),
    "IMG_0005.jpg": (60.0, 14.0, "2013:06:04 13:37:44", 260.0, 75.0),  # same second as 0004
    "IMG_0004.jpg": (50.0, 12.0, "2013:06:04 13:37:44", 255.0, 71.0),
}


def make_geotagged(d: Path) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    for name, (e, n, when, yaw, h) in GEO_FRAMES.items():
        write_geotagged(d / name, east=e, north=n, when=when,
                        xmp={"Height": h, "Heading": yaw, "RollAngle": 2.0, "PitchAngle": -1.5})
    return d


def test_geotagged_pure_helpers():
    # lengths of one degree on WGS84 (the usual series): 111132.954 - 559.822 cos 2phi + 1.175 cos 4phi
    # north, 111412.84 cos phi - 93.5 cos 3phi + 0.118 cos 5phi east
    for lat in (0.0, 41.0, 45.0, 70.0):
        p = math.radians(lat)
        x, y = local_east_north(np.array([lat + 0.0005, lat]), np.array([0.0, 0.001]), lat, 0.0)
        assert y[0] * 2000 == pytest.approx(111132.954 - 559.822 * math.cos(2 * p) + 1.175 * math.cos(4 * p), abs=0.05)
        assert x[1] * 1000 == pytest.approx(111412.84 * math.cos(p) - 93.5 * math.cos(3 * p) + 0.118 * math.cos(5 * p), abs=0.05)
    # nose north: image columns (vehicle +x) point east; nose east: columns point south
    assert theta_from_heading(0.0) == pytest.approx(0.0)
    assert theta_from_heading(90.0) == pytest.approx(-math.pi / 2)
    assert float(wrap_angle(theta_from_heading(180.0) - math.pi)) == pytest.approx(0.0, abs=1e-12)
    t, moved = spread_ties(np.array([0.0, 5.0, 5.0, 5.0, 9.0]), np.ones(5))
    np.testing.assert_allclose(t, [0, 5, 5 + 1 / 3, 5 + 2 / 3, 9])
    assert moved == 2


def test_import_geotagged(tmp_path):
    src = make_geotagged(tmp_path / "imgs")
    out = tmp_path / "log"
    res = run("import-geotagged", src, out, "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    # time order, the two frames of 13:37:44 in file-name order and spread within the second
    assert lg.frame_images == [f"images/IMG_000{i}.jpg" for i in range(1, 6)]
    np.testing.assert_allclose(lg.frame_t, [0, 6, 11, 15, 15.5])
    for name in GEO_FRAMES:  # byte for byte
        assert (out / "images" / name).read_bytes() == (src / name).read_bytes()
    # positions: east/north metres from the first frame
    ll = np.array([geo_of(src / f"IMG_000{i}.jpg") for i in range(1, 6)])
    x, y = local_east_north(ll[:, 0], ll[:, 1], ll[0, 0], ll[0, 1])
    np.testing.assert_allclose(lg.odometry[:, 1], x, atol=1e-6)
    np.testing.assert_allclose(lg.odometry[:, 2], y, atol=1e-6)
    order = sorted(GEO_FRAMES.values(), key=lambda v: (v[2], v[0]))
    np.testing.assert_allclose(lg.odometry[:, 1], [v[0] for v in order], atol=0.5)  # the helper's rough degrees
    np.testing.assert_allclose(lg.odometry[:, 2], [v[1] for v in order], atol=0.5)
    np.testing.assert_allclose(lg.odometry[:, 3], wrap_angle(-np.radians([v[3] for v in order])), atol=1e-6)
    # camera: fx = f / sensor width * width, median height
    cam = lg.camera
    assert cam.fx == pytest.approx(4.3 / 6.2 * 64, rel=1e-5) and cam.fy == cam.fx
    assert (cam.cx, cam.cy) == (31.5, 23.5)
    assert cam.height_m == pytest.approx(70.0, abs=1e-4)
    frames = (out / "frames.csv").read_text().splitlines()
    assert frames[0] == "t,image,height_m"
    np.testing.assert_allclose([float(r.split(",")[2]) for r in frames[1:]], [v[4] for v in order], atol=1e-4)
    att = np.loadtxt(out / "attitude.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(att[:, 1:3], np.radians([[2.0, -1.5]] * 5), atol=1e-6)

    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["frames"] == 5 and rep["time_ties_spread"] == 1 and rep["yaw_sources"] == {"sensefly:Heading": 5}


def test_import_geotagged_missing_gps(tmp_path):
    src = make_geotagged(tmp_path / "imgs")
    write_geotagged(src / "IMG_0006.jpg", east=None, xmp={"Height": 70.0, "Heading": 70.0})
    res = run("import-geotagged", src, tmp_path / "log")
    assert res.exit_code == 2
    line = one_error_line(res)
    assert f"{src}: missing metadata: GPS position in 1 of 6 frames" in line
    assert "GPS:Latitude" in line and "e.g. IMG_0006.jpg" in line
    assert not (tmp_path / "log").exists()


def test_import_geotagged_height_fallback_and_sizes(tmp_path):
    src = tmp_path / "imgs"
    src.mkdir()
    for i in range(3):  # EXIF only: heading from GPS:ImgDirection, no XMP height
        write_geotagged(src / f"IMG_{i}.jpg", east=10.0 * i, when=f"2013:06:04 13:37:{10 + i:02d}")
    write_geotagged(src / "IMG_3.jpg", east=30.0, when="2013:06:04 13:37:13", size=(128, 96))  # same aspect: resized
    write_geotagged(src / "IMG_4.jpg", east=40.0, when="2013:06:04 13:37:14", size=(64, 64))   # other aspect: dropped
    for p in src.iterdir():
        buf = oiio.ImageBuf(str(p))
        buf.specmod().attribute("GPS:ImgDirection", 90.0)
        tmp = p.with_suffix(".tmp.jpg")
        assert buf.write(str(tmp))
        tmp.replace(p)
    res = run("import-geotagged", src, tmp_path / "nolog", "-q")
    assert res.exit_code == 2
    line = one_error_line(res)
    assert "height above ground in 4 of 4 frames" in line and "sensefly:Height" in line and "--height-m" in line
    out = tmp_path / "log"
    res = run("import-geotagged", src, out, "--height-m", 50, "--focal-mm", 5.0, "--sensor-width-mm", 6.0,
              "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    assert lg.frame_images == ["images/IMG_0.jpg", "images/IMG_1.jpg", "images/IMG_2.jpg", "images/IMG_3.png"]
    assert oiio.ImageInput.open(str(out / "images/IMG_3.png")).spec().width == 64
    assert lg.camera.height_m == 50 and lg.camera.fx == pytest.approx(5.0 / 6.0 * 64)
    np.testing.assert_allclose(lg.odometry[:, 3], -math.pi / 2)

    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["frames_found"] == 5 and rep["frames_resized"] == 1
    assert [d["image"] for d in rep["frames_dropped"]] == ["IMG_4.jpg"]
    assert rep["yaw_sources"] == {"GPS:ImgDirection": 4}


# --- import-geotagged: DJI metadata, missing fields, heading options -----------------------

# file name -> (east, north, time, gimbal yaw, flight yaw, gimbal pitch, gimbal roll, relative altitude)
DJI_FRAMES = {
    "DJI_0001.JPG": (0.0, 0.0, "2021:05:17 10:02:01", -92.5, -95.0, -90.0, 0.0, 35.2),
    "DJI_0002.JPG": (-12.0, 0.5, "2021:05:17 10:02:04", -91.0, -93.0, -90.0, 0.2, 35.6),
    "DJI_0003.JPG": (-24.0, 0.8, "2021:05:17 10:02:07", -90.4, -89.0, -85.0, -0.3, 36.1),
    "DJI_0004.JPG": (-24.5, 12.0, "2021:05:17 10:02:12", 88.0, 85.5, -90.0, 0.0, 34.8),
    "DJI_0005.JPG": (-12.0, 12.5, "2021:05:17 10:02:15", 179.5, 91.0, -89.5, 0.1, 35.0),
}
DJI_FOCAL, DJI_FOCAL35 = 8.8, 24  # a 1" sensor (13.2 mm wide) behind a 24 mm-equivalent lens


def make_dji(d: Path, *, gimbal: bool = True, flight: bool = True) -> Path:
    """A DJI-style set: EXIF GPS, FocalLength and FocalLengthIn35mmFilm (no focal plane
    resolution), drone-dji XMP written as rdf:Description attributes like DJI's."""
    d.mkdir(parents=True, exist_ok=True)
    for name, (e, n, when, gyaw, fyaw, gpitch, groll, rel) in DJI_FRAMES.items():
        xmp = {"AbsoluteAltitude": 312.85, "RelativeAltitude": rel}
        if gimbal:
            xmp.update(GimbalYawDegree=gyaw, GimbalPitchDegree=gpitch, GimbalRollDegree=groll)
        if flight:
            xmp.update(FlightYawDegree=fyaw, FlightPitchDegree=-2.3, FlightRollDegree=1.5)
        write_geotagged(d / name, east=e, north=n, when=when, xmp=xmp, xmp_ns="drone-dji",
                        focal=DJI_FOCAL, focal_plane=False, focal35=DJI_FOCAL35)
    return d


def test_dji_xmp_as_openimageio_presents_it(tmp_path):
    make_dji(tmp_path / "imgs")
    spec = oiio.ImageInput.open(str(tmp_path / "imgs" / "DJI_0003.JPG")).spec()
    assert spec.getattribute("drone-dji:GimbalYawDegree") == pytest.approx(-90.4, abs=1e-4)  # "-90.40" as a number
    assert spec.getattribute("drone-dji:RelativeAltitude") == pytest.approx(36.1, abs=1e-4)  # "+36.10"
    assert spec.getattribute("drone-dji:GimbalPitchDegree") == pytest.approx(-85.0)
    assert spec.getattribute("Exif:FocalLengthIn35mmFilm") == DJI_FOCAL35
    assert spec.getattribute("Exif:FocalPlaneXResolution") is None


def test_import_geotagged_dji(tmp_path):
    """A DJI set imports with no option: gimbal yaw, relative altitude, sensor width from the 35 mm equivalent."""
    src = make_dji(tmp_path / "imgs")
    out = tmp_path / "log"
    res = run("import-geotagged", src, out, "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    # GPS positions are absolute priors, each frame's own (not steps of a dead reckoning)
    assert lg.odometry_model == {"kind": "absolute", "sigma_m": 3.0, "heading_sigma_rad": 1.0}
    names = list(DJI_FRAMES)
    assert lg.frame_images == [f"images/{n}" for n in names]
    np.testing.assert_allclose(lg.frame_t, [0, 3, 6, 11, 14])
    v = np.array([DJI_FRAMES[n][:2] + DJI_FRAMES[n][3:] for n in names], float)  # east, north, gyaw, fyaw, pitch, roll, rel
    np.testing.assert_allclose(lg.odometry[:, 1], v[:, 0] - v[0, 0], atol=0.5)
    np.testing.assert_allclose(lg.odometry[:, 2], v[:, 1] - v[0, 1], atol=0.5)
    # the gimbal's yaw (not the aircraft's), theta = -yaw as for senseFly's heading
    np.testing.assert_allclose(wrap_angle(lg.odometry[:, 3] + np.radians(v[:, 2])), 0.0, atol=1e-6)
    # height above the take-off point, sensor width 36 mm * 8.8 / 24 = 13.2 mm
    frames = (out / "frames.csv").read_text().splitlines()
    np.testing.assert_allclose([float(r.split(",")[2]) for r in frames[1:]], v[:, 6], atol=1e-4)
    assert lg.camera.height_m == pytest.approx(35.2, abs=1e-4)
    assert lg.camera.fx == pytest.approx(DJI_FOCAL / 13.2 * 64, rel=1e-5)
    # attitude: the gimbal's, pitch as tilt from nadir (DJI's -90 is 0), yaw the one used
    att = np.loadtxt(out / "attitude.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(att[:, 1], np.radians(v[:, 5]), atol=1e-6)
    np.testing.assert_allclose(att[:, 2], np.radians(v[:, 4] + 90.0), atol=1e-6)
    np.testing.assert_allclose(att[:, 3], np.radians(v[:, 2]), atol=1e-6)
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["yaw_sources"] == {"drone-dji:GimbalYawDegree": 5} and rep["heading_from"] == "metadata"
    assert rep["height_sources"] == {"drone-dji:RelativeAltitude": 5}
    assert "take-off point" in rep["height_assumption"]
    assert rep["attitude_sources"] == {"drone-dji:Gimbal": 5}
    assert rep["sensor_width_mm"] == pytest.approx(13.2, abs=1e-5)
    assert "FocalLengthIn35mmFilm" in rep["sensor_width_source"] and "36 mm" in rep["sensor_width_source"]
    assert "FocalLengthIn35mmFilm" in lg.meta["source"]["sensor_width_source"]


def test_dji_heading_convention_matches_sensefly(tmp_path):
    """The same compass yaws give the same theta whether DJI's gimbal, DJI's flight or senseFly's heading carries them."""
    thetas = {}
    make_dji(tmp_path / "gimbal")
    make_dji(tmp_path / "flight", gimbal=False)
    sf = tmp_path / "sensefly"
    sf.mkdir()
    for name, (e, n, when, gyaw, *_rest, rel) in DJI_FRAMES.items():
        write_geotagged(sf / name, east=e, north=n, when=when, xmp={"Height": rel, "Heading": gyaw})
    for kind in ("gimbal", "flight", "sensefly"):
        res = run("import-geotagged", tmp_path / kind, tmp_path / f"log-{kind}", "--report", tmp_path / f"{kind}.json", "-q")
        assert res.exit_code == 0, res.output
        thetas[kind] = read_drive_log(tmp_path / f"log-{kind}").odometry[:, 3]
    np.testing.assert_allclose(thetas["gimbal"], thetas["sensefly"], atol=1e-6)
    flight_yaw = np.array([v[4] for v in DJI_FRAMES.values()])
    np.testing.assert_allclose(wrap_angle(thetas["flight"] - theta_from_heading(flight_yaw)), 0.0, atol=1e-6)
    rep = json.loads((tmp_path / "flight.json").read_text())
    assert rep["yaw_sources"] == {"drone-dji:FlightYawDegree": 5}
    assert rep["attitude_sources"] == {"drone-dji:Flight": 5}  # no gimbal record: the aircraft's attitude


def make_bare(d: Path) -> Path:
    """Five frames flying east with EXIF GPS and little else: the first has a senseFly heading
    and no 35 mm equivalent focal length, the fourth no focal length; none has a height or a
    focal plane resolution."""
    d.mkdir(parents=True, exist_ok=True)
    for i in range(5):
        write_geotagged(d / f"DJI_{i + 1:04d}.JPG", east=15.0 * i, when=f"2021:05:17 10:02:{10 + 2 * i:02d}",
                        focal=None if i == 3 else DJI_FOCAL, focal_plane=False,
                        focal35=None if i == 0 else DJI_FOCAL35, xmp={"Heading": 80.0} if i == 0 else None)
    return d


def test_import_geotagged_reports_every_missing_field(tmp_path):
    src = make_bare(tmp_path / "imgs")
    res = run("import-geotagged", src, tmp_path / "log")
    assert res.exit_code == 2
    line = one_error_line(res)
    assert line.startswith(f"mosaicmap: error: {src}: missing metadata: ")
    assert "heading in 4 of 5 frames (" in line and "e.g. DJI_0002.JPG; give --heading-deg DEG or --heading-from track)" in line
    assert "drone-dji:GimbalYawDegree" in line
    assert "height above ground in 5 of 5 frames (" in line and "drone-dji:RelativeAltitude" in line
    assert "e.g. DJI_0001.JPG; give --height-m M)" in line
    assert "focal length in 1 of 5 frames (no Exif:FocalLength; e.g. DJI_0004.JPG; give --focal-mm MM)" in line
    assert "sensor width in 2 of 5 frames (" in line and "e.g. DJI_0001.JPG; give --sensor-width-mm MM)" in line
    assert not (tmp_path / "log").exists()

    # the options supply them all: a fixed heading overrides even the frame that has one
    out = tmp_path / "fixed"
    res = run("import-geotagged", src, out, "--heading-deg", 30, "--height-m", 40, "--focal-mm", DJI_FOCAL,
              "--sensor-width-mm", 13.2, "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    np.testing.assert_allclose(lg.odometry[:, 3], -math.radians(30))
    assert lg.camera.height_m == 40 and lg.camera.fx == pytest.approx(DJI_FOCAL / 13.2 * 64)
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["yaw_sources"] == {"--heading-deg": 5} and rep["heading_from"] == "fixed"
    assert rep["height_sources"] == {"--height-m": 5} and rep["height_assumption"] is None
    assert rep["sensor_width_source"] == "--sensor-width-mm"

    # heading from the GPS track (flying east: yaw 90, image columns point south)
    out = tmp_path / "track"
    res = run("import-geotagged", src, out, "--heading-from", "track", "--height-m", 40, "--focal-mm", DJI_FOCAL,
              "--sensor-width-mm", 13.2, "-q")
    assert res.exit_code == 0, res.output
    np.testing.assert_allclose(read_drive_log(out).odometry[:, 3], -math.pi / 2, atol=0.02)

    # --focal-mm also serves the 35 mm equivalent of the frame without Exif:FocalLength
    res = run("import-geotagged", src, tmp_path / "log2", "--heading-deg", 30, "--height-m", 40, "--focal-mm", DJI_FOCAL)
    line = one_error_line(res)
    assert res.exit_code == 2 and not any(f"{w} in" in line for w in ("heading", "height above ground", "focal length"))
    assert "sensor width in 1 of 5 frames (" in line and "e.g. DJI_0001.JPG" in line


def test_import_geotagged_height_not_positive_and_heading_options(tmp_path):
    src = make_dji(tmp_path / "imgs")
    p = src / "DJI_0002.JPG"  # on the ground at the take-off point: RelativeAltitude +0.00
    write_geotagged(p, east=-12.0, north=0.5, when="2021:05:17 10:02:04", xmp_ns="drone-dji",
                    xmp={"GimbalYawDegree": -91.0, "RelativeAltitude": 0.0}, focal=DJI_FOCAL, focal_plane=False,
                    focal35=DJI_FOCAL35)
    res = run("import-geotagged", src, tmp_path / "log")
    assert res.exit_code == 2
    assert "height above ground in 1 of 5 frames" in one_error_line(res)
    res = run("import-geotagged", src, tmp_path / "log", "--height-m", 30, "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    frames = (tmp_path / "log" / "frames.csv").read_text().splitlines()
    np.testing.assert_allclose([float(r.split(",")[2]) for r in frames[1:]], [35.2, 30.0, 36.1, 34.8, 35.0], atol=1e-4)
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["height_sources"] == {"drone-dji:RelativeAltitude": 4, "--height-m": 1}
    res = run("import-geotagged", src, tmp_path / "log3", "--heading-deg", 10, "--heading-from", "track")
    assert res.exit_code == 2 and "--heading-deg" in one_error_line(res)


def test_track_headings():
    # east, east, a turn north, north: central differences, one-sided at the ends
    yaw = track_headings(np.array([0.0, 5, 10, 10, 10]), np.array([0.0, 0, 0, 5, 10]))
    np.testing.assert_allclose(yaw, [90, 90, 45, 0, 0], atol=1e-9)
    # a hovering frame (within 1 m of its neighbours) looks past them
    yaw = track_headings(np.array([0.0, 0.3, 0.5, 0.5]), np.array([0.0, 0.0, -0.2, -8.0]))
    assert yaw[0] == pytest.approx(math.degrees(math.atan2(0.5, -8.0)))
    assert yaw[3] == pytest.approx(180.0, abs=5)
    with pytest.raises(ValueError, match="1 m apart"):
        track_headings(np.zeros(4), np.array([0.0, 0.2, 0.1, 0.3]))


# --- real data -----------------------------------------------------------------------------


@pytest.mark.realdata
def test_real_tile_grid(tmp_path):
    d = require(REAL / "lscm_speckle_3x4")
    out = tmp_path / "tiles"
    m = 0.0025
    res = run("import-tiles", d / "TileConfiguration.txt", out, "--pixel-size", m,
              "--peer", d / "TileConfiguration.registered.txt", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    assert len(lg.frame_images) == 12
    xy = tile_positions_from_poses(lg.odometry, (1024, 1024), m)
    np.testing.assert_allclose(np.unique(np.round(xy[:, 0])), [0, 921, 1842, 2763])
    np.testing.assert_allclose(np.unique(np.round(xy[:, 1])), [0, 921, 1842])
    # file order is row by row, left to right (the file names A005..A008 run the other way)
    steps = np.diff(lg.odometry[:, 1:3], axis=0) / m
    np.testing.assert_allclose(np.delete(steps, [3, 7], axis=0), [[921.0, 0.0]] * 9)
    np.testing.assert_allclose(steps[[3, 7]], [[-2763.0, -921.0]] * 2)
    peer = read_pose_csv(out / "peer_positions.csv")
    ref = np.array([(x, y) for _, x, y in read_tile_configuration(d / "TileConfiguration.registered.txt")])
    np.testing.assert_allclose(tile_positions_from_poses(peer, (1024, 1024), m), ref, atol=1e-6)
    assert np.abs(ref - xy).max() < 6.0  # the peer moved the tiles by a few pixels at most


def _seneca_log(tmp_path_factory) -> Path:
    d = require(REAL / "seneca_drone" / "images")
    out = tmp_path_factory.mktemp("seneca") / "drone"
    res = run("import-geotagged", d, out, "-q")
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def seneca(tmp_path_factory) -> Path:
    return _seneca_log(tmp_path_factory)


@pytest.mark.realdata
def test_real_drone_log(seneca):
    lg = read_drive_log(seneca)
    assert len(lg.frame_images) == 167  # every frame kept: all 1200 x 900 with GPS, heading and height
    assert np.all(np.diff(lg.frame_t) > 0)
    xy = lg.odometry[:, 1:3]
    extent = xy.max(axis=0) - xy.min(axis=0)
    assert np.all((extent > 200) & (extent < 1000)), extent
    assert 60 < lg.camera.height_m < 80
    assert lg.camera.height_m / lg.camera.fx == pytest.approx(0.085, rel=0.1)  # ground metres per pixel
    # parallel flight lines: most steps run along one axis, in both directions
    d = np.diff(xy, axis=0)
    ang = np.arctan2(d[:, 1], d[:, 0])
    axis = 0.5 * np.angle(np.mean(np.exp(2j * ang)))
    along = np.abs(np.cos(ang - axis)) > math.cos(math.radians(25))
    assert along.mean() > 0.6
    fwd = np.cos(ang[along] - axis) > 0
    assert 0.15 < fwd.mean() < 0.85  # legs flown both ways (more frames on the upwind legs)
    # heading agrees with the direction of travel on straight legs (theta = -yaw, image top = nose)
    nose = lg.odometry[:-1, 3] + math.pi / 2
    assert np.median(np.abs(wrap_angle(ang - nose))) < math.radians(20)


@pytest.mark.realdata
def test_real_drone_yaw_convention_from_images(seneca):
    """Image motion between overlapping frames, rotated by theta, points along the GPS displacement."""
    lg = read_drive_log(seneca)
    sift = cv2.SIFT_create(1500)
    err = []
    for i in (70, 92, 93, 102, 154, 156):  # consecutive frames on straight legs with good texture
        imgs = [cv2.resize(cv2.imread(str(lg.image_path(k)), cv2.IMREAD_GRAYSCALE), (600, 450),
                           interpolation=cv2.INTER_AREA) for k in (i, i + 1)]
        (ka, da), (kb, db) = (sift.detectAndCompute(im, None) for im in imgs)
        pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.75 * p[1].distance]
        pa = np.float32([ka[g.queryIdx].pt for g in good])
        pb = np.float32([kb[g.trainIdx].pt for g in good])
        t, inl = cv2.estimateAffinePartial2D(pa, pb, method=cv2.RANSAC, ransacReprojThreshold=3)
        assert t is not None and inl.sum() >= 30
        c = cv2.invertAffineTransform(t) @ np.array([299.5, 224.5, 1.0])  # frame i+1's centre in frame i
        xv, yv = c[0] - 299.5, -(c[1] - 224.5)  # vehicle frame of i: columns +x, rows -y
        d = lg.odometry[i + 1, 1:3] - lg.odometry[i, 1:3]
        err.append(wrap_angle(math.atan2(d[1], d[0]) - (lg.odometry[i, 3] + math.atan2(yv, xv))))
    # roll and pitch (up to ~18 deg) scatter single pairs; a wrong convention is off by >= 90 deg
    assert abs(np.median(err)) < math.radians(20), np.degrees(err)
