"""Hostile or unlucky input ends in one clear line, never a traceback: image caps checked
before decoding, tags checked before the commit, storage errors named, paths kept inside the
log, wild calibration and odometry refused, stale temporaries removed, `gc` frees what no
branch or tag reaches."""

from __future__ import annotations

import errno
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from conftest import write_small_log
from mapstore.repository import MapRepository
from pipeline.cli import cli
from pipeline.errors import BadInput, WriteFailed, one_line, writing


def run(*args, **kw):
    return CliRunner().invoke(cli, [str(a) for a in args], **kw)


def error_lines(res) -> list[str]:
    """The lines of a run's stderr (what a user sees besides the normal output)."""
    return [ln for ln in res.stderr.splitlines() if ln.strip()]


def assert_one_line(res, code: int, *expect: str) -> str:
    lines = error_lines(res)
    assert res.exit_code == code, (res.exit_code, res.output, res.stderr)
    assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.output + res.stderr
    for e in expect:
        assert e in lines[0], lines[0]
    return lines[0]


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (old, text)
    path.write_text(text.replace(old, new, 1))


def _line(path: Path, n: int, new: str) -> None:
    lines = path.read_text().splitlines()
    lines[n] = new
    path.write_text("\n".join(lines) + "\n")


def huge_header_png(path: Path, width: int = 30000, height: int = 30000) -> Path:
    """A small PNG whose header declares ``width x height`` grey pixels (the data stream holds
    a few rows only: decoding it would allocate the declared size first)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * (width + 1) * 4)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return path


# --- item 3: image caps before decoding ---------------------------------------------------


def test_huge_header_png_refused_before_decoding(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    huge_header_png(log / "images" / "000002.png")
    assert (log / "images" / "000002.png").stat().st_size < 1_000_000
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 2, "000002.png", "30000x30000", "max_image_pixels")


def test_image_byte_cap_from_config(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[ingest]\nmax_image_bytes = 200\n")
    res = run("ingest", log, "-w", tmp_path / "w", "--config", cfg, "-q")
    assert_one_line(res, 2, "000000.png", "max_image_bytes = 200")


def test_every_outside_image_reader_checks_the_header(tmp_path: Path):
    from pipeline.images import read_grey, read_raw
    from pipeline.importers.geotagged import read_geotag
    from pipeline.importers.tiles import _image_shape

    png = huge_header_png(tmp_path / "huge.png")
    readers = [read_grey, read_raw, read_geotag, lambda p: _image_shape(p, "tiles.txt")]
    for reader in readers:
        with pytest.raises(BadInput, match="max_image_pixels"):
            reader(png)


def test_flat_field_image_is_capped(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    huge_header_png(log / "flat.png")
    _edit(log / "drive.toml", "pixel_size_m = 0.0025", 'pixel_size_m = 0.0025\nflat_field = "flat.png"')
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 2, "flat.png", "max_image_pixels")


# --- item 6: tags checked before the commit -----------------------------------------------


@pytest.fixture
def repo_with_tag(tmp_path: Path) -> MapRepository:
    """A repository with one commit on main, tagged ``t1``."""
    repo = MapRepository.create(str(tmp_path / "map"))
    s = repo.writable("main")
    root = zarr.open_group(s.store, mode="a")
    root.create_array("x", shape=(4,), dtype="i4")[:] = np.arange(4)
    sid = s.commit("first")
    repo.repo.create_tag("t1", sid)
    return repo


def test_build_with_existing_tag_leaves_no_untagged_version(tmp_path: Path, repo_with_tag):
    log = write_small_log(tmp_path / "log", n_frames=4)
    before = [si.id for si in repo_with_tag.repo.ancestry(branch="main")]
    res = run("build", log, "--map", repo_with_tag.url, "-w", tmp_path / "w", "--tag", "t1", "-q")
    assert_one_line(res, 2, "--tag", "'t1' exists already")
    assert [si.id for si in repo_with_tag.repo.ancestry(branch="main")] == before
    assert not (tmp_path / "w" / "ingest").exists()  # refused before any stage ran


@pytest.mark.parametrize("name,expect", [
    ("main", "is the name of"),
    ("a\nb", "control character"),
    ("x" * 300, "300 characters"),
    ("bell\x07", "control character"),
    ("latest", "shadow"),
])
def test_build_tag_names_refused_before_stages(tmp_path: Path, repo_with_tag, name: str, expect: str):
    log = write_small_log(tmp_path / "log", n_frames=4)
    res = run("build", log, "--map", repo_with_tag.url, "-w", tmp_path / "w", "--tag", name, "-q")
    line = assert_one_line(res, 2, "--tag", expect)
    assert "\x07" not in line and "\n" not in line
    assert not (tmp_path / "w" / "ingest").exists()


@pytest.mark.parametrize("name,expect", [
    ("main", "name of a branch"),
    ("a\nb", "control character"),
    ("y" * 101, "101 characters"),
    ("t1", "exists already"),
])
def test_tag_command_refuses_bad_names(repo_with_tag, name: str, expect: str):
    res = run("tag", repo_with_tag.url, "t1", name)
    assert_one_line(res, 2, expect)
    assert set(repo_with_tag.tags()) == {"t1"}


def test_publish_checks_the_tag_before_committing(repo_with_tag):
    """The in-lock check publish runs just before its commit (a tag taken meanwhile)."""
    from pipeline.stages.publish import _new_tag

    with pytest.raises(BadInput, match="exists already"):
        _new_tag(repo_with_tag, "t1", {"tag_format": "v{date}-{n}"}, "main")
    with pytest.raises(BadInput, match="branch"):
        _new_tag(repo_with_tag, "nightly", {"tag_format": "v{date}-{n}"}, "nightly")
    with pytest.raises(BadInput, match="tag_format"):
        _new_tag(repo_with_tag, None, {"tag_format": "t1"}, "main")
    assert _new_tag(repo_with_tag, None, {"tag_format": "v{n}"}, "main") == "v1"


# --- item 7: storage errors as one line ---------------------------------------------------


def test_disk_full_in_work_directory_is_one_line(tmp_path: Path, monkeypatch):
    import pipeline.stages.build

    log = write_small_log(tmp_path / "log", n_frames=4)
    work = tmp_path / "w"

    def full(path, obj):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(pipeline.stages.build, "write_json_atomic", full)
    res = run("ingest", log, "-w", work, "-q")
    assert_one_line(res, 1, "manifest.json", "cannot write the work directory", "No space left on device")
    assert not (work / "ingest").exists()  # nothing half-written
    assert not list(work.glob(".tmp-*"))


@pytest.fixture
def tiny_tmpfs(tmp_path: Path):
    """A 64 KiB tmpfs (a real full disk); skipped where mounting is not allowed (not root, no
    CAP_SYS_ADMIN)."""
    import subprocess

    mnt = tmp_path / "tiny"
    mnt.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN)")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def test_disk_full_for_real(tmp_path: Path, tiny_tmpfs: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    res = run("ingest", log, "-w", tiny_tmpfs / "w", "-q")
    assert_one_line(res, 1, str(tiny_tmpfs / "w"), "cannot write the work directory", "No space left on device")
    assert [p.name for p in (tiny_tmpfs / "w").iterdir()] == [".lock"]  # nothing half-written


@pytest.fixture
def synth_map(tmp_path: Path) -> str:
    """A small synthetic map with two versions ("one", "two"): export and apply-delta inputs."""
    import copy

    from mapstore.grid import MapGrid
    from pipeline.config import load_config
    from pipeline.testing.synthmap import periodic_texture, publish_raster, texture_tile_fn

    cfg = copy.deepcopy(load_config(None))
    cfg["map"].update(chunk_px=64, shard_px=256)
    url = str(tmp_path / "smap")
    grid = MapGrid(0.0, 0.6, 0.0025, 256, 256)
    tex = periodic_texture(2, 256)
    publish_raster(url, grid, texture_tile_fn(tex, grid), cfg=cfg, tag="one")
    publish_raster(url, grid, lambda *w: texture_tile_fn(tex, grid)(*w) * 0.5, cfg=cfg, tag="two")
    return url


def test_export_and_apply_delta_storage_errors_are_one_line(tmp_path: Path, synth_map: str):
    long_out = tmp_path / ("b" * 300 + ".zip")
    res = run("export", synth_map, long_out, "--version", "one")
    assert_one_line(res, 1, "File name too long", "export was writing the bundle")
    base, delta = tmp_path / "one.zip", tmp_path / "delta.zip"
    assert run("export", synth_map, base, "--version", "one").exit_code == 0
    res = run("export", synth_map, delta, "--version", "two", "--since", "one")
    assert res.exit_code == 0, res.output
    res = run("apply-delta", base, delta, tmp_path / ("p" * 300 + ".zip"))
    assert_one_line(res, 1, "File name too long", "apply-delta was writing the patched bundle")
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".zip") == ["delta.zip", "one.zip"]


def test_export_onto_a_full_disk(tmp_path: Path, synth_map: str, tiny_tmpfs: Path):
    res = run("export", synth_map, tiny_tmpfs / "map.zip", "--version", "one")
    assert_one_line(res, 1, "No space left on device", "export was writing the bundle")
    assert list(tiny_tmpfs.iterdir()) == []  # nothing half-written


def test_storage_error_of_the_repository_is_one_line(repo_with_tag, monkeypatch):
    """icechunk reports the OS error inside its own message ("(os error 28)")."""
    class IcechunkLike(Exception):
        pass

    def full(self, name, **kw):
        raise IcechunkLike("x object store error Generic LocalFileSystem error: Unable to copy data to file: "
                           "No space left on device (os error 28)\n  |-> more\n")

    monkeypatch.setattr(MapRepository, "check_new_tag", full)
    res = run("tag", repo_with_tag.url, "t1", "t2")
    assert_one_line(res, 1, "No space left on device", "map repository")

    def denied(self, name, **kw):
        raise PermissionError(errno.EACCES, "Permission denied", "/srv/map/refs/tag.t2")

    monkeypatch.setattr(MapRepository, "check_new_tag", denied)
    res = run("tag", repo_with_tag.url, "t1", "t2")
    assert_one_line(res, 1, "/srv/map/refs/tag.t2", "Permission denied", "map repository")


def test_writing_names_the_path_and_what():
    with pytest.raises(WriteFailed, match=r"^/w/x: cannot write the work directory: No space left on device"):
        with writing("the work directory", "/w"):
            raise OSError(errno.ENOSPC, "No space left on device", "/w/x")
    with pytest.raises(WriteFailed, match=r"^s3://b/m: cannot write the map repository: .*EDQUOT"):
        with writing("the map repository", "s3://b/m"):
            raise RuntimeError(f"quota (os error {errno.EDQUOT})")
    with pytest.raises(KeyError):  # not a storage error: left alone
        with writing("the work directory", "/w"):
            raise KeyError("x")


def test_work_directory_name_too_long(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    res = run("ingest", log, "-w", tmp_path / ("w" * 300), "-q")
    assert_one_line(res, 1, "File name too long", "work directory")


def test_permission_denied_work_directory(tmp_path: Path):
    if os.geteuid() == 0:
        pytest.skip("runs as root: permissions do not apply")
    log = write_small_log(tmp_path / "log", n_frames=4)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        res = run("ingest", log, "-w", ro / "w", "-q")
        assert_one_line(res, 1, "Permission denied", "work directory")
    finally:
        ro.chmod(0o700)


def test_unexpected_exception_is_one_line_traceback_only_with_v(tmp_path: Path, monkeypatch):
    from dataclasses import replace

    import pipeline.stages.build

    def boom(*a, **kw):
        raise RuntimeError("something\nunexpected")

    monkeypatch.setitem(pipeline.stages.build.STAGES, "ingest", replace(pipeline.stages.build.STAGES["ingest"], run=boom))
    log = write_small_log(tmp_path / "log", n_frames=4)
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 1, "internal error", "RuntimeError: something", "rerun with -v")
    res = run("-v", "ingest", log, "-w", tmp_path / "w2", "-q")
    assert res.exit_code == 1 and "Traceback" in res.stderr


def test_one_line_escapes_control_characters_and_numpy_reprs():
    assert one_line("a\nb\x1b[31m\ufeff") == "a\\nb\\x1b[31m\\ufeff"
    assert one_line("t np.float64(2.4000000000000004) s, n np.int64(3)") == "t 2.4000000000000004 s, n 3"


# --- item 8: paths stay inside the log ----------------------------------------------------


def test_image_symlink_outside_refused_unless_configured(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    outside = tmp_path / "elsewhere.png"
    os.replace(log / "images" / "000001.png", outside)
    (log / "images" / "000001.png").symlink_to(outside)
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 2, "frames.csv:3", "000001.png", "outside the log directory", "follow_symlinks")
    cfg = tmp_path / "c.toml"
    cfg.write_text("[ingest]\nfollow_symlinks = true\n")
    res = run("ingest", log, "-w", tmp_path / "w", "--config", cfg, "-q")
    assert res.exit_code == 0, res.output


def test_symlink_inside_the_log_is_fine(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    (log / "images" / "000001.png").unlink()
    (log / "images" / "000001.png").symlink_to(log / "images" / "000000.png")
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert res.exit_code == 0, res.output


def test_images_dir_symlink_outside_refused(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    os.replace(log / "images", tmp_path / "shared-images")
    (log / "images").symlink_to(tmp_path / "shared-images")
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 2, "frames.csv:2", "outside the log directory")


@pytest.mark.parametrize("value", ["../x.png", "ABS", "link.png"])
def test_flat_field_path_outside_refused(tmp_path: Path, value: str):
    """Each names an existing image outside the log: a relative path up, an absolute path, a link."""
    log = write_small_log(tmp_path / "log", n_frames=4)
    (tmp_path / "x.png").write_bytes((log / "images" / "000000.png").read_bytes())
    (log / "link.png").symlink_to(tmp_path / "x.png")
    value = str(tmp_path / "x.png") if value == "ABS" else value
    _edit(log / "drive.toml", "pixel_size_m = 0.0025", f'pixel_size_m = 0.0025\nflat_field = "{value}"')
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 2, "camera.flat_field")


@pytest.mark.parametrize("name", ["frames.csv", "odometry.csv", "drive.toml"])
def test_log_file_symlink_outside_refused(tmp_path: Path, name: str):
    log = write_small_log(tmp_path / "log", n_frames=4)
    os.replace(log / name, tmp_path / name)
    (log / name).symlink_to(tmp_path / name)
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert_one_line(res, 2, name, "outside the log directory")


# --- item 9: tracebacks and messages ------------------------------------------------------

INTRINSICS = "fx = 100.0\nfy = 100.0\ncx = 32.0\ncy = 24.0\nheight_m = 0.3"

BAD = [
    ("missing-frames-csv", lambda d: (d / "frames.csv").unlink(), ["frames.csv", "file not found"]),
    ("image-name-too-long", lambda d: _line(d / "frames.csv", 1, "0.1,images/" + "a" * 300 + ".png"),
     ["frames.csv:2", "File name too long"]),
    ("fx-1e12", lambda d: _edit(d / "drive.toml", "pixel_size_m = 0.0025", INTRINSICS.replace("fx = 100.0", "fx = 1e12")),
     ["camera.fx", "beyond any camera"]),
    ("fx-fy-sliver", lambda d: _edit(d / "drive.toml", "pixel_size_m = 0.0025", INTRINSICS.replace("fx = 100.0", "fx = 1e5")),
     ["camera.fx", "fx / fy"]),
    ("odometry-1e300", lambda d: _line(d / "odometry.csv", 3, "0.1,1e300,0.0,0.0"), ["odometry.csv:4", "x = 1e300"]),
    ("theta-1e300", lambda d: _line(d / "odometry.csv", 3, "0.1,0.0,0.0,-1e300"), ["odometry.csv:4", "theta"]),
    ("huge-distortion", lambda d: _edit(d / "drive.toml", "pixel_size_m = 0.0025", INTRINSICS + "\nk1 = 1e6\nk2 = 1e9"),
     ["camera.k1", "beyond any lens"]),
    ("log-id-comma", lambda d: _edit(d / "drive.toml", 'id = "log"', 'id = "a,b"'), ["log.id", "','"]),
    ("log-id-newline", lambda d: _edit(d / "drive.toml", 'id = "log"', 'id = "a\\nb"'), ["log.id", "'\\n'"]),
    ("frame-time-plain", lambda d: _line(d / "frames.csv", 4, "2.4000000000000004,images/000003.png"),
     ["frames.csv:5", "frame time 2.4000000000000004 s"]),
    ("control-character", lambda d: _line(d / "frames.csv", 0, "t\x1b[31m,image"), ["frames.csv:1", "\\x1b"]),
    ("frames-latin1", lambda d: (d / "frames.csv").write_bytes(b"t,image\n0.1,images/\xe9.png\n"), ["frames.csv", "UTF-8"]),
]


@pytest.mark.parametrize("mutate,expect", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_input_is_one_clear_line(tmp_path: Path, mutate, expect: list[str]):
    log = write_small_log(tmp_path / "log", n_frames=4)
    mutate(log)
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    line = assert_one_line(res, 2, *expect)
    assert "np.float64" not in line and "\x1b" not in line


@pytest.mark.parametrize("name", ["frames.csv", "odometry.csv"])
def test_utf8_bom_is_accepted(tmp_path: Path, name: str):
    log = write_small_log(tmp_path / "log", n_frames=4)
    (log / name).write_bytes(b"\xef\xbb\xbf" + (log / name).read_bytes())
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert res.exit_code == 0, res.output


def test_wild_distortion_within_bounds_maps_nothing(tmp_path: Path):
    """Distortion within the per-coefficient bound that still folds the whole image away."""
    log = write_small_log(tmp_path / "log", n_frames=4)
    _edit(log / "drive.toml", "pixel_size_m = 0.0025", INTRINSICS + "\nk1 = -10.0\nk2 = 10.0")
    res = run("ingest", log, "-w", tmp_path / "w", "-q")
    assert res.exit_code in (0, 2), res.output
    assert "Traceback" not in res.output + res.stderr
    if res.exit_code == 2:
        assert len(error_lines(res)) == 1


# --- item 10: leftovers --------------------------------------------------------------------


def test_rerun_removes_stale_temporaries(tmp_path: Path):
    log = write_small_log(tmp_path / "log", n_frames=4)
    work = tmp_path / "w"
    stale = work / ".tmp-ingest-k1ll3d"
    (stale / "frames.zarr").mkdir(parents=True)
    (stale / "frames.zarr" / "junk").write_bytes(b"x" * 1000)
    (work / ".tmp-manifest.json-123").write_text("{")
    (work / ".old-register-99").mkdir()
    res = run("ingest", log, "-w", work, "-q")
    assert res.exit_code == 0, res.output
    assert not [p.name for p in work.iterdir() if p.name.startswith((".tmp-", ".old-"))]
    assert (work / "ingest" / "manifest.json").is_file()


def _commit(repo: MapRepository, value: int, tag: str | None = None) -> str:
    s = repo.writable("main")
    root = zarr.open_group(s.store, mode="a")
    a = root.require_array("x", shape=(64, 64), chunks=(16, 16), dtype="i4")
    a[:] = value
    sid = s.commit(f"value {value}")
    if tag:
        repo.repo.create_tag(tag, sid)
    return sid


def _value(repo: MapRepository, version: str) -> int:
    root = zarr.open_group(repo.readonly(version).store, mode="r")
    vals = np.unique(root["x"][:])
    assert vals.size == 1
    return int(vals[0])


def test_gc_frees_unreachable_snapshots_and_keeps_versions(tmp_path: Path):
    repo = MapRepository.create(str(tmp_path / "map"))
    _commit(repo, 1, "v1")
    untagged = _commit(repo, 2)
    v3 = _commit(repo, 3, "v3")
    lost = _commit(repo, 4)  # then the branch is reset: nothing reaches it
    repo.repo.reset_branch("main", v3)
    repo.repo.create_branch("side", v3)
    side_tip = _commit_on(repo, "side", 5)
    du = sum(p.stat().st_size for p in (tmp_path / "map").rglob("*") if p.is_file())

    history = [si.id for si in repo.repo.ancestry(branch="main")]
    assert untagged in history

    res = run("gc", repo.url, "--older-than", "0", "--dry-run", "--expire")
    assert res.exit_code == 0, res.output
    assert "would expire 1 untagged snapshot" in res.output and "would free" in res.output
    assert repo.repo.lookup_snapshot(lost).id == lost  # dry run: nothing changed

    res = run("gc", repo.url, "--older-than", "7d")
    assert res.exit_code == 0 and "freed 0 bytes" in res.output, res.output  # all too young

    res = run("gc", repo.url, "--older-than", "0")
    assert res.exit_code == 0, res.output
    freed = int(res.output.split("freed ")[1].split(" bytes")[0])
    assert freed > 0 and "1 snapshots" in res.output
    after = sum(p.stat().st_size for p in (tmp_path / "map").rglob("*") if p.is_file())
    assert after < du
    repo = MapRepository.open(repo.url)
    with pytest.raises(Exception):
        repo.readonly(lost)
    assert [si.id for si in repo.repo.ancestry(branch="main")] == history  # the history is untouched
    assert _value(repo, untagged) == 2

    res = run("gc", repo.url, "--older-than", "0", "--expire")
    assert res.exit_code == 0 and "expired 1 untagged snapshot" in res.output, res.output
    repo = MapRepository.open(repo.url)
    assert set(repo.tags()) == {"v1", "v3"}
    assert _value(repo, "v1") == 1 and _value(repo, "v3") == 3 and _value(repo, "latest") == 3
    assert repo.resolve(None, "side") == side_tip and _value(repo, side_tip) == 5
    with pytest.raises(Exception):
        repo.readonly(untagged)


def _commit_on(repo: MapRepository, branch: str, value: int) -> str:
    s = repo.writable(branch)
    zarr.open_group(s.store, mode="a")["x"][:] = value
    return s.commit(f"value {value}")


def test_gc_refuses_a_bad_age(repo_with_tag):
    res = run("gc", repo_with_tag.url, "--older-than", "soon")
    assert_one_line(res, 2, "--older-than")
