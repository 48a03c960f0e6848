"""Fuzzing drive logs: mutated logs through ingest (in-process, and a few through the CLI) and
through a build. Every outcome is one of two classes: accepted, or a clean BadInput (exit
code 2) naming the culprit file of the log; never any other exception or a traceback.

Property-based with hypothesis at a fixed seed (``derandomize``): the same examples on every
run. Budget: ``MOSAICMAP_FUZZ_EXAMPLES`` examples for ingest (default 220; the build and CLI
properties take a tenth each); ``bench/fuzz_logs.py`` runs a longer budget.
"""

from __future__ import annotations

import os
import shutil
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import write_small_log
from pipeline.stages.build import run_build
from pipeline.cli import cli
from pipeline.config import load_config
from pipeline.errors import BadInput, JobFailed
from pipeline.images import write_grey

EXAMPLES = int(os.environ.get("MOSAICMAP_FUZZ_EXAMPLES", "220"))
FUZZ = settings(derandomize=True, deadline=None, max_examples=EXAMPLES, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FEW = settings(FUZZ, max_examples=max(10, EXAMPLES // 10))
BUILD = settings(FUZZ, max_examples=max(6, EXAMPLES // 18))

N_FRAMES = 4
ODO_ROWS = 11  # write_small_log: odometry at 20 Hz over 0..0.5 s

# --- the base log ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def base_log(tmp_path_factory) -> Path:
    return write_small_log(tmp_path_factory.mktemp("fuzzbase") / "log", n_frames=N_FRAMES, size=(48, 40))


@pytest.fixture(scope="module")
def cfg() -> dict:
    c = load_config()
    c["ingest"]["workers"] = 1
    c["ingest"]["quality"]["min_textured_fraction"] = 0.0  # tiny frames: not the gates under test
    return c


# --- nasty values and mutations --------------------------------------------------------------

NASTY_TEXT = st.sampled_from([
    "", " ", "nan", "NaN", "inf", "-inf", "1e300", "-1e300", "1e-320", "0", "-0", "-1", "0x10", "1_0", "abc",
    "1,5", '"1"', "\x00", "\x1b[31m", "\n", "\r", "\ufeff", "é", "𝟘", "../x", "/etc/passwd", "a" * 300,
    "images/000001.png", "images/", "images/000001.png\x00", "2.4000000000000004", "1e308", "1" * 400,
])
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e300, -1e300, 1e12, 1e-12, 5e-324, 2.4000000000000004]),
    st.integers(min_value=-(10**30), max_value=10**30),
)
TOML_VALUES = st.one_of(
    NUMBERS.map(lambda v: repr(v) if isinstance(v, int) else {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(v), repr(v))),
    NASTY_TEXT.map(lambda s: '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
                   .replace("\r", "\\r").replace("\x00", "\\u0000").replace("\x1b", "\\u001b") + '"'),
    st.sampled_from(["true", "[]", "[1.0]", "[0.1, 0.2]", "[nan, 1.0]", "{}", "{a = 1}", "1979-05-27"]),
)


def _csv_lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


def _write_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8", newline="")


@st.composite
def csv_field_edit(draw, name: str, columns: int, rows: int):
    row = draw(st.integers(0, rows))  # 0 = the header
    col = draw(st.integers(0, columns - 1))
    value = draw(st.one_of(NASTY_TEXT, NUMBERS.map(repr)))

    def apply(d: Path) -> None:
        lines = _csv_lines(d / name)
        fields = lines[row].split(",")
        fields[col % len(fields)] = value
        lines[row] = ",".join(fields)
        _write_lines(d / name, lines)
    return f"{name}[{row},{col}]={value!r}", apply


@st.composite
def csv_structure_edit(draw, name: str):
    kind = draw(st.sampled_from(["bom", "crlf", "latin1", "utf16", "truncate", "empty", "header-only",
                                 "blank-lines", "extra-column", "drop-column", "reverse-rows", "duplicate-row",
                                 "random-bytes", "swap-header", "nul-bytes", "height-column"]))
    cut = draw(st.integers(0, 400))
    junk = draw(st.binary(min_size=0, max_size=64))
    heights = draw(st.lists(NUMBERS.map(repr), min_size=1, max_size=1))

    def apply(d: Path) -> None:
        p = d / name
        data = p.read_bytes()
        lines = data.decode().splitlines()
        if kind == "bom":
            p.write_bytes(b"\xef\xbb\xbf" + data)
        elif kind == "crlf":
            p.write_bytes(data.replace(b"\n", b"\r\n"))
        elif kind == "latin1":
            p.write_bytes(data.replace(b"images", "imagés".encode("latin-1")))
        elif kind == "utf16":
            p.write_bytes(data.decode().encode("utf-16"))
        elif kind == "truncate":
            p.write_bytes(data[: cut % max(1, len(data))])
        elif kind == "empty":
            p.write_bytes(b"")
        elif kind == "header-only":
            _write_lines(p, lines[:1])
        elif kind == "blank-lines":
            _write_lines(p, [x for ln in lines for x in (ln, "", " ,")])
        elif kind == "extra-column":
            _write_lines(p, [ln + ",x" for ln in lines])
        elif kind == "drop-column":
            _write_lines(p, [ln.rsplit(",", 1)[0] for ln in lines])
        elif kind == "reverse-rows":
            _write_lines(p, lines[:1] + lines[:0:-1])
        elif kind == "duplicate-row":
            _write_lines(p, lines[:2] + lines[1:])
        elif kind == "random-bytes":
            p.write_bytes(data[: cut % max(1, len(data))] + junk + data[cut % max(1, len(data)):])
        elif kind == "swap-header":
            h = lines[0].split(",")
            _write_lines(p, [",".join(h[::-1])] + lines[1:])
        elif kind == "nul-bytes":
            p.write_bytes(data.replace(b",", b",\x00", 1))
        elif kind == "height-column":
            _write_lines(p, [lines[0] + ",height_m"] + [ln + "," + heights[0] for ln in lines[1:]])
    return f"{name}:{kind}:{cut}", apply


@st.composite
def toml_edit(draw):
    key = draw(st.sampled_from([
        "camera.pixel_size_m", "camera.model", "camera.fx", "camera.k1", "camera.vignetting", "camera.flat_field",
        "camera.height_m", "log.id", "format_version", "route.id", "odometry.error_gradient", "camera.unknown",
        "intrinsics", "garbage", "truncate", "drop-camera"]))
    value = draw(TOML_VALUES)
    cut = draw(st.integers(0, 200))

    def apply(d: Path) -> None:
        p = d / "drive.toml"
        text = p.read_text()
        if key == "garbage":
            p.write_text(text + f"\n{value} = = [\n")
        elif key == "truncate":
            p.write_bytes(p.read_bytes()[:cut])
        elif key == "drop-camera":
            p.write_text(text.split("[camera]")[0])
        elif key == "intrinsics":
            p.write_text(text.replace("pixel_size_m = 0.0025",
                                      f"fx = {value}\nfy = 60.0\ncx = 24.0\ncy = 20.0\nheight_m = 0.15"))
        elif key == "format_version":
            p.write_text(text.replace("format_version = 1", f"format_version = {value}"))
        else:
            table, field = key.split(".")
            line = f"{field} = {value}"
            if f"[{table}]" in text:
                lines = [ln for ln in text.splitlines() if not ln.startswith(f"{field} =")]
                i = lines.index(f"[{table}]")
                lines.insert(i + 1, line)
                p.write_text("\n".join(lines) + "\n")
            else:
                p.write_text(text + f"\n[{table}]\n{line}\n")
    return f"drive.toml:{key}={value}", apply


def _png_header(width: int, height: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


@st.composite
def image_edit(draw):
    i = draw(st.integers(0, N_FRAMES - 1))
    kind = draw(st.sampled_from(["garbage", "truncate", "empty", "huge-header", "zero-header", "directory",
                                 "other-size", "rgb", "rgba16", "tiny", "symlink-out", "symlink-loop",
                                 "images-dir-out", "flip-bytes", "dangling"]))
    cut = draw(st.integers(0, 2000))
    w = draw(st.sampled_from([0, 1, 2**31 - 1, 30000, 65535]))

    def apply(d: Path) -> None:
        p = d / "images" / f"{i:06d}.png"
        data = p.read_bytes() if p.is_file() else b"\x89PNG"
        outside = d.parent / f"outside-{i}.png"
        if kind == "garbage":
            p.write_bytes(data[:8] + bytes((b * 7 + 3) % 256 for b in data[8:]))
        elif kind == "truncate":
            p.write_bytes(data[: cut % max(1, len(data))])
        elif kind == "empty":
            p.write_bytes(b"")
        elif kind == "huge-header":
            p.write_bytes(_png_header(30000, 30000))
        elif kind == "zero-header":
            p.write_bytes(_png_header(w, max(1, w // 2)))
        elif kind == "directory":
            p.unlink()
            p.mkdir()
        elif kind == "other-size":
            write_grey(p, np.full((40, 47), 100.0, np.float32))
        elif kind == "rgb":
            from pipeline.images import write_image
            write_image(p, np.full((40, 48, 3), 90, np.uint8))
        elif kind == "rgba16":
            from pipeline.images import write_image
            write_image(p, np.full((40, 48, 4), 30000, np.uint16))
        elif kind == "tiny":
            write_grey(p, np.full((1, 1), 100.0, np.float32))
        elif kind == "symlink-out":
            outside.write_bytes(data)
            p.unlink()
            p.symlink_to(outside)
        elif kind == "symlink-loop":
            p.unlink()
            p.symlink_to(p)
        elif kind == "images-dir-out":
            target = d.parent / "outside-images"
            if not target.exists():
                os.replace(d / "images", target)
                (d / "images").symlink_to(target)
        elif kind == "flip-bytes":
            b = bytearray(data)
            b[cut % len(b)] ^= 0xFF
            p.write_bytes(bytes(b))
        elif kind == "dangling":
            p.unlink()
            p.symlink_to(d / "nowhere.png")
    return f"image {i}:{kind}:{cut}:{w}", apply


def mutations():
    return st.one_of(
        csv_field_edit("frames.csv", 2, N_FRAMES),
        csv_field_edit("odometry.csv", 4, ODO_ROWS),
        csv_structure_edit("frames.csv"),
        csv_structure_edit("odometry.csv"),
        toml_edit(),
        image_edit(),
        st.sampled_from(["frames.csv", "odometry.csv", "drive.toml", "images", "."]).map(_remove),
    )


def _remove(name: str):
    """Remove a file of the log, its images directory, or the log itself (a file left in its place)."""
    def apply(d: Path) -> None:
        p = d / name
        if name == ".":
            shutil.rmtree(d)
            d.write_text("x")
        elif p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    return f"remove {name}", apply


# --- outcome classes -------------------------------------------------------------------------


def apply_all(log: Path, muts) -> None:
    """Apply the mutations in order; one that no longer applies (its file is gone, the log is
    a file now) is skipped."""
    for _, apply in muts:
        try:
            apply(log)
        except (OSError, ValueError, IndexError, UnicodeError):
            pass


def _fresh_copy(base: Path) -> Path:
    root = Path(tempfile.mkdtemp(prefix="fuzz-", dir=base.parent.parent))
    return Path(shutil.copytree(base, root / "log", symlinks=True))


def assert_clean(log: Path, fn, *, allow_job_failed: bool = False) -> str:
    """Run ``fn``; the outcome must be "accepted", or a BadInput naming a file of ``log`` (or the
    map pixel size the log's calibration implies), or with ``allow_job_failed`` a JobFailed.
    Any other exception fails the test."""
    try:
        fn()
        return "accepted"
    except BadInput as e:
        where = e.where
        assert str(log) in where or where.startswith("config[map.pixel_size_m]"), f"culprit not named: {e}"
        return "refused"
    except JobFailed:
        if allow_job_failed:
            return "failed"
        raise


def _ingest(log: Path, cfg: dict, work: Path):
    return lambda: run_build([log], work, cfg, until="ingest", only="ingest", quiet=True)


@FUZZ
@given(muts=st.lists(mutations(), min_size=1, max_size=3))
def test_mutated_logs_through_ingest(base_log: Path, cfg: dict, muts):
    log = _fresh_copy(base_log)
    try:
        apply_all(log, muts)
        assert_clean(log, _ingest(log, cfg, log.parent / "work"))
    finally:
        shutil.rmtree(log.parent, ignore_errors=True)


@FEW
@given(muts=st.lists(mutations(), min_size=1, max_size=2))
def test_mutated_logs_through_the_cli(base_log: Path, muts):
    log = _fresh_copy(base_log)
    try:
        apply_all(log, muts)
        res = CliRunner().invoke(cli, ["ingest", str(log), "-w", str(log.parent / "work"), "-q"])
        assert res.exit_code in (0, 2), (res.exit_code, res.stderr, res.exception)
        assert "Traceback" not in res.stderr and "internal error" not in res.stderr, res.stderr
        if res.exit_code == 2:
            lines = [ln for ln in res.stderr.splitlines() if ln.startswith("mosaicmap: error:")]
            assert len(lines) == 1 and str(log) in lines[0], res.stderr
            assert all(c.isprintable() for c in lines[0]), repr(lines[0])
    finally:
        shutil.rmtree(log.parent, ignore_errors=True)


@BUILD
@given(muts=st.lists(st.one_of(csv_field_edit("odometry.csv", 4, ODO_ROWS), csv_field_edit("frames.csv", 2, N_FRAMES),
                               image_edit(), toml_edit()), min_size=1, max_size=2))
def test_mutated_logs_through_build(base_log: Path, cfg: dict, muts):
    """Ingest, register and optimize (no map repository): BadInput naming the log, or the job's
    own clean failure (JobFailed), or a result."""
    log = _fresh_copy(base_log)
    try:
        apply_all(log, muts)
        assert_clean(log, lambda: run_build([log], log.parent / "work", cfg, quiet=True), allow_job_failed=True)
    finally:
        shutil.rmtree(log.parent, ignore_errors=True)


def test_the_base_log_is_accepted(base_log: Path, cfg: dict, tmp_path: Path):
    """The unmutated log passes (else every property above would test only refusals)."""
    log = Path(shutil.copytree(base_log, tmp_path / "log"))
    assert assert_clean(log, _ingest(log, cfg, tmp_path / "work")) == "accepted"
