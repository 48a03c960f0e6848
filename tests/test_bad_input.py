"""Bad input: every case exits with code 2 and one line naming the culprit, and writes nothing."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from conftest import write_small_log
from pipeline.cli import cli


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{old!r} not in {path}"
    path.write_text(text.replace(old, new, 1))


def _line(path: Path, n: int, new: str) -> None:
    lines = path.read_text().splitlines()
    lines[n] = new
    path.write_text("\n".join(lines) + "\n")


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


# Each case: (id, mutation(log_dir), text the message must contain).
CASES = [
    ("missing-drive-toml", lambda d: (d / "drive.toml").unlink(), "drive.toml"),
    ("toml-syntax", lambda d: (d / "drive.toml").write_text("format_version = = 1\n"), "not valid TOML"),
    ("unknown-version", lambda d: _edit(d / "drive.toml", "format_version = 1", "format_version = 7"), "format_version"),
    ("missing-calibration", lambda d: _edit(d / "drive.toml", "pixel_size_m = 0.0025", ""), "camera.pixel_size_m"),
    ("unknown-model", lambda d: _edit(d / "drive.toml", '"downward"', '"fisheye"'), "camera.model"),
    ("negative-pixel-size", lambda d: _edit(d / "drive.toml", "pixel_size_m = 0.0025", "pixel_size_m = -1.0"), "camera.pixel_size_m"),
    ("frames-header", lambda d: _line(d / "frames.csv", 0, "time,file"), "frames.csv:1"),
    ("frames-not-number", lambda d: _line(d / "frames.csv", 3, "abc,images/000002.png"), "frames.csv:4"),
    ("frames-nan", lambda d: _line(d / "frames.csv", 3, "nan,images/000002.png"), "frames.csv:4"),
    ("frames-duplicate-t", lambda d: _line(d / "frames.csv", 3, "0.2,images/000002.png"), "duplicate timestamp"),
    ("frames-backwards", lambda d: _line(d / "frames.csv", 3, "0.15,images/000002.png"), "goes backwards"),
    ("frames-field-count", lambda d: _line(d / "frames.csv", 2, "0.2,images/000001.png,extra"), "frames.csv:3"),
    ("missing-image", lambda d: (d / "images" / "000004.png").unlink(), "000004.png"),
    ("corrupt-image", lambda d: (d / "images" / "000003.png").write_bytes(b"not an image at all" * 20), "000003.png"),
    ("truncated-image", lambda d: _truncate(d / "images" / "000005.png"), "000005.png"),
    ("odometry-inf", lambda d: _line(d / "odometry.csv", 5, "0.2,inf,0.0,0.0"), "odometry.csv:6"),
    ("odometry-backwards", lambda d: _line(d / "odometry.csv", 5, "0.01,0.1,0.0,0.0"), "odometry.csv:6"),
    ("odometry-missing", lambda d: (d / "odometry.csv").unlink(), "odometry.csv"),
    ("frame-outside-odometry", lambda d: _line(d / "frames.csv", 8, "9.5,images/000007.png"), "outside the odometry time span"),
    ("frames-empty", lambda d: (d / "frames.csv").write_text("t,image\n"), "has no frames"),
    ("both-calibrations", lambda d: _edit(d / "drive.toml", "pixel_size_m = 0.0025", "pixel_size_m = 0.0025\nfx = 100.0"), "not both"),
    ("image-escapes-log", lambda d: _line(d / "frames.csv", 2, "0.2,../outside.png"), "frames.csv:3"),
]


@pytest.mark.parametrize("mutate,expect", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_log_exit_2(tmp_path: Path, mutate, expect: str):
    log_dir = write_small_log(tmp_path / "log")
    mutate(log_dir)
    work = tmp_path / "work"
    res = CliRunner().invoke(cli, ["build", str(log_dir), "--workdir", str(work), "--until", "ingest", "--quiet"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("mosaicmap: error:")]
    assert len(lines) == 1, res.output
    assert expect in lines[0], lines[0]
    # Nothing that looks complete was left behind.
    assert not (work / "ingest" / "manifest.json").exists()
    assert not [p for p in work.glob("*") if p.name not in (".lock",)]


def test_bad_image_skip_mode_lists_reason(tmp_path: Path):
    log_dir = write_small_log(tmp_path / "log")
    (log_dir / "images" / "000003.png").write_bytes(b"garbage" * 10)
    cfg = tmp_path / "skip.toml"
    cfg.write_text('[ingest]\non_bad_image = "skip"\nmax_bad_fraction = 0.2\n')
    report = tmp_path / "r.json"
    res = CliRunner().invoke(
        cli, ["build", str(log_dir), "-w", str(tmp_path / "w"), "--until", "ingest", "--config", str(cfg), "--report", str(report), "-q"]
    )
    assert res.exit_code == 0, res.output
    import json

    rep = json.loads(report.read_text())
    assert rep["ingest"]["frames_accepted"] == 7
    (rej,) = rep["ingest"]["rejected"]
    assert rej["frame"] == 3 and "unreadable image" in rej["reason"]


def test_missing_log_dir(tmp_path: Path):
    res = CliRunner().invoke(cli, ["build", str(tmp_path / "nope"), "-w", str(tmp_path / "w")])
    assert res.exit_code == 2 and "drive log directory not found" in res.output


def test_unknown_config_key(tmp_path: Path, small_log: Path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[ingest]\nworkerz = 3\n")
    res = CliRunner().invoke(cli, ["build", str(small_log), "-w", str(tmp_path / "w"), "--config", str(cfg)])
    assert res.exit_code == 2 and "[ingest] workerz: unknown key" in res.output


def test_wrong_config_type(tmp_path: Path, small_log: Path):
    cfg = tmp_path / "c.toml"
    cfg.write_text('[map]\npixel_size_m = "big"\n')
    res = CliRunner().invoke(cli, ["config", "show", "--config", str(cfg)])
    assert res.exit_code == 2 and "[map] pixel_size_m: must be a number" in res.output


def test_unknown_until_stage(tmp_path: Path, small_log: Path):
    res = CliRunner().invoke(cli, ["build", str(small_log), "-w", str(tmp_path / "w"), "--until", "rendr"])
    assert res.exit_code == 2 and "--until" in res.output
    # render exists but needs a map repository
    res = CliRunner().invoke(cli, ["build", str(small_log), "-w", str(tmp_path / "w"), "--until", "render"])
    assert res.exit_code == 2 and "--map" in res.output


def test_frame_of_other_size(tmp_path: Path):
    log_dir = write_small_log(tmp_path / "log")
    other = write_small_log(tmp_path / "other", size=(32, 32))
    shutil.copy(other / "images" / "000002.png", log_dir / "images" / "000002.png")
    res = CliRunner().invoke(cli, ["build", str(log_dir), "-w", str(tmp_path / "w"), "--until", "ingest", "-q"])
    assert res.exit_code == 2 and "000002.png" in res.output and "32x32" in res.output


def test_map_pixel_far_finer_than_camera(tmp_path: Path):
    log_dir = write_small_log(tmp_path / "log")
    cfg = tmp_path / "c.toml"
    cfg.write_text("[map]\npixel_size_m = 0.000001\n")
    res = CliRunner().invoke(cli, ["build", str(log_dir), "-w", str(tmp_path / "w"), "--config", str(cfg), "--until", "ingest"])
    assert res.exit_code == 2 and "map.pixel_size_m" in res.output and "finer" in res.output


def test_config_show_quotes_keys():
    from pipeline.config import dump_toml
    import tomllib

    doc = {"source": {"sensefly:Heading": "x", "plain": 1}}
    assert tomllib.loads(dump_toml(doc)) == doc


def test_one_bad_image_of_a_long_log_is_skipped_by_default(tmp_path: Path):
    """The defaults: an unusable image is dropped with its reason and the build goes on while
    they stay within [ingest] max_bad_fraction of the log; past it, one line naming the file."""
    import json

    log_dir = write_small_log(tmp_path / "log")
    (log_dir / "images" / "000003.png").write_bytes(b"garbage" * 10)
    _truncate(log_dir / "images" / "000006.png")
    report = tmp_path / "r.json"
    cfg = tmp_path / "frac.toml"
    cfg.write_text("[ingest]\nmax_bad_fraction = 0.25\n")  # 2 of these 8 frames may be unusable
    res = CliRunner().invoke(cli, ["build", str(log_dir), "-w", str(tmp_path / "w"), "--until", "ingest",
                                   "--config", str(cfg), "--report", str(report), "-q"])
    assert res.exit_code == 0, res.output
    rep = json.loads(report.read_text())
    assert rep["ingest"]["frames_accepted"] == 6
    assert [r["frame"] for r in rep["ingest"]["rejected"]] == [3, 6]
    assert all("image" in r["reason"] for r in rep["ingest"]["rejected"])
    # a third one is past the fraction: exit 2, one line naming it
    (log_dir / "images" / "000001.png").write_bytes(b"")
    res = CliRunner().invoke(cli, ["build", str(log_dir), "-w", str(tmp_path / "w2"), "--until", "ingest",
                                   "--config", str(cfg), "-q"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("mosaicmap: error:")]
    assert len(lines) == 1 and "max_bad_fraction" in lines[0] and "3 of the log's 8 frames" in lines[0], lines
    # strict mode stops at the first
    cfg.write_text('[ingest]\non_bad_image = "fail"\n')
    res = CliRunner().invoke(cli, ["build", str(log_dir), "-w", str(tmp_path / "w3"), "--until", "ingest",
                                   "--config", str(cfg), "-q"])
    assert res.exit_code == 2 and "000001.png" in res.output and "max_bad_fraction" not in res.output, res.output
