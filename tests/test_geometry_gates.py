"""Sane geometry before publish (pipeline/geometry_gate.py, pipeline/anchor.py).

A frame whose pose rests on its prior alone and jumps more than the vehicle could move is
dropped with its reason (not rendered, not published); the rendered extent is checked
against the linked frames' extent by the publish gate; a log that matches no part of the
map stops after a fixed number of failed anchor attempts, with one line.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from mapstore.layout import read_floor, read_poses
from mapstore.repository import MapRepository
from pipeline.config import load_config
from pipeline.errors import JobFailed
from pipeline.geometry_gate import JumpParams, prior_spikes, speed_cap, wild_unlinked
from pipeline.stages.publish import check_gates
from conftest import invoke

AREA = "1.5x1.5"
WILD_M = 1000.0


def _floor(repo: Path) -> zarr.Group:
    return zarr.open_group(MapRepository.open(str(repo)).readonly(None).store, mode="r")


def _snapshots(repo: Path) -> int:
    r = MapRepository.open(str(repo))
    return len(list(r.repo.ancestry(branch="main")))


# --- the speed model on synthetic trajectories (fast) ------------------------------------


def _line(n: int = 300, speed: float = 1.0, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    t = dt * np.arange(n)
    return np.column_stack([speed * t, np.zeros(n), np.zeros(n)]), t


def test_a_spike_of_the_prior_is_found_and_nothing_else():
    prior, t = _line()
    prior[100, 0] += WILD_M  # one wild row
    prior[200:203, 1] -= 50.0  # three wild rows in a run
    assert np.flatnonzero(prior_spikes(prior, t, 1.0, JumpParams())).tolist() == [100, 200, 201, 202]
    prior[0, 0] -= WILD_M  # and the first: cut off from the rest by one jump
    prior[-2:, 1] += WILD_M  # and the last two
    assert np.flatnonzero(prior_spikes(prior, t, 1.0, JumpParams())).tolist() == [0, 100, 200, 201, 202, 298, 299]
    clean, t = _line()
    assert not prior_spikes(clean, t, 1.0, JumpParams()).any()
    assert not prior_spikes(prior, t, 1.0, JumpParams(speed_factor=0.0)).any()  # off


def test_a_raster_scans_row_returns_are_no_spike():
    # 5 rows of 20 tiles scanned left to right, each row return a long jump one way
    cols, rows = 20, 5
    xy = np.column_stack([np.tile(np.arange(cols), rows), np.repeat(np.arange(rows), cols)]).astype(float)
    prior = np.column_stack([xy, np.zeros(len(xy))])
    assert not prior_spikes(prior, np.arange(len(xy), dtype=float), 0.5, JumpParams()).any()


def test_an_unlinked_frame_far_from_its_linked_neighbours_is_dropped_with_its_reason():
    poses, t = _line()
    log_of = np.zeros(len(t), int)
    linked = np.ones(len(t), bool)
    linked[[0, 50, 120, 121, 122, 299]] = False
    poses[0, 0] -= WILD_M  # a wild first frame: one side to judge it by
    poses[50, 1] += WILD_M  # a wild frame in the middle
    # 120..122 placed by their prior on a blank stretch: where the vehicle could be
    caps = [speed_cap(poses, t, JumpParams())]
    out = wild_unlinked(poses, t, log_of, linked, caps, [1.0], JumpParams())
    assert sorted(out) == [0, 50]
    assert "no registration link" in out[50] and "speed cap" in out[50] and "1e+03 m" in out[50]
    # a raster scan's first tile of a row, unlinked: far from the row before, next to its own row
    cols, rows = 20, 5
    xy = np.column_stack([np.tile(np.arange(cols), rows), np.repeat(np.arange(rows), cols)]).astype(float)
    grid = np.column_stack([xy, np.zeros(len(xy))])
    tt = np.arange(len(xy), dtype=float)
    lk = np.ones(len(xy), bool)
    lk[2 * cols] = False
    caps = [speed_cap(grid, tt, JumpParams())]
    assert wild_unlinked(grid, tt, np.zeros(len(xy), int), lk, caps, [0.5], JumpParams()) == {}


def _report(linked: list[float], extent: list[float]) -> dict:
    return {"geometry": {"linked_extent_m": linked, "extent_m": extent, "frame_diagonal_m": 1.0}}


def test_the_publish_gate_refuses_an_extent_beyond_the_linked_frames():
    pub = load_config()["publish"]
    linked = [0.0, 0.0, 5.0, 5.0]
    # default tolerance: 0.5 x 5 m + 2 frame diagonals of 1 m = 4.5 m on any side
    check_gates(_report(linked, [-4.0, 0.0, 9.0, 5.0]), pub)
    with pytest.raises(JobFailed) as e:
        check_gates(_report(linked, [0.0, 0.0, 5.0 + WILD_M, 5.0]), pub)
    msg = str(e.value)
    assert "\n" not in msg and "max_extent_growth_fraction" in msg and "not published" in msg and "1000" in msg
    # the render's own extent, when there is one, is the one checked
    rep = _report(linked, linked)
    rep["render"] = {"extent_m": [0.0, -WILD_M, 5.0, 5.0]}
    with pytest.raises(JobFailed):
        check_gates(rep, pub)


# --- end to end on simulated floors ------------------------------------------------------


def _wild_row(log: Path, frame: int, dx: float) -> None:
    """Move the odometry row at frame ``frame``'s time by ``dx`` metres in x."""
    with open(log / "frames.csv", newline="") as f:
        t_frame = float(list(csv.DictReader(f))[frame]["t"])
    lines = (log / "odometry.csv").read_text().splitlines()
    ts = np.array([float(ln.split(",")[0]) for ln in lines[1:]])
    k = int(np.argmin(np.abs(ts - t_frame))) + 1
    fields = lines[k].split(",")
    fields[1] = repr(float(fields[1]) + dx)
    lines[k] = ",".join(fields)
    (log / "odometry.csv").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def floor_a(tmp_path_factory):
    """Floor A simulated and published as version 1 of a map."""
    root = tmp_path_factory.mktemp("geom")
    a = root / "A"
    r = invoke("simulate", "floor", a, "--area", AREA, "--seed", "1", "--quiet")
    assert r.exit_code == 0, r.output
    r = invoke("build", a, "--map", root / "map", "-w", root / "wa", "--report", root / "ra.json", "--quiet")
    assert r.exit_code == 0, r.output
    return {"root": root, "A": a, "map": root / "map", "ra": json.loads((root / "ra.json").read_text())}


@pytest.mark.slow
def test_a_wild_odometry_row_is_dropped_and_the_map_keeps_its_size(floor_a, tmp_path):
    log = tmp_path / "L"
    shutil.copytree(floor_a["A"], log)
    toml = (log / "drive.toml").read_text()
    (log / "drive.toml").write_text(toml.replace('id = "A"', 'id = "L"'))
    n = len((log / "frames.csv").read_text().splitlines()) - 1
    mid = n // 2
    _wild_row(log, mid, WILD_M)
    _wild_row(log, 0, -WILD_M)  # and the first frame: only one side to judge it by
    repo = tmp_path / "map"
    r = invoke("build", log, "--map", repo, "-w", tmp_path / "w", "--report", tmp_path / "r.json", "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "r.json").read_text())
    geo = rep["geometry"]
    dropped = {d["frame"]: d["reason"] for d in geo["dropped"]}
    assert sorted(dropped) == [0, mid] and geo["frames_dropped"] == 2
    assert "1000 m off the path" in dropped[mid] and "speed cap" in dropped[mid]
    assert "1000 m off the path" in dropped[0] and "no registration link" in dropped[0]
    assert rep["registration"]["prior_spikes"] == ["L frame 0", f"L frame {mid}"]
    # not rendered: the map is no larger than floor A's (its first frame is missing), not a kilometre wide
    grid, grid_a = read_floor(_floor(repo)).grid, read_floor(_floor(floor_a["map"])).grid
    assert grid.height <= grid_a.height and grid_a.width - 50 <= grid.width <= grid_a.width
    assert grid.width * grid.pixel_size < 5.0
    assert rep["render"]["frames_dropped"] == 2 and geo["extent_growth_m"] == 0.0
    # not published: the map's pose table holds the other frames only
    poses = read_poses(_floor(repo))
    assert len(poses) == n - 2 and sorted(set(range(n)) - set(poses.frame.tolist())) == [0, mid]
    assert np.abs(poses.pose[:, :2]).max() < 5.0
    assert (tmp_path / "w" / "optimize" / "dropped.csv").read_text().count("\n") == 3


@pytest.mark.slow
def test_a_log_of_another_floor_stops_after_the_configured_anchor_attempts(floor_a, tmp_path, monkeypatch):
    import pipeline.anchor as anchor

    b = tmp_path / "B"
    r = invoke("simulate", "floor", b, "--area", AREA, "--seed", "2", "--quiet")
    assert r.exit_code == 0, r.output
    repo = tmp_path / "map"
    shutil.copytree(floor_a["map"], repo)
    before = _snapshots(repo)
    calls = []
    real = anchor.register_pair
    monkeypatch.setattr(anchor, "register_pair", lambda *a, **k: calls.append(1) or real(*a, **k))
    r = invoke("build", b, "--map", repo, "-w", tmp_path / "w", "--quiet")
    limit = load_config()["register"]["map_max_failed_anchors"]
    assert r.exit_code == 1, r.output
    n = len((b / "frames.csv").read_text().splitlines()) - 1
    line = [ln for ln in r.output.splitlines() if "match the map" in ln]
    assert len(line) == 1 and f"B: 0 of {n} frames match the map {repo} (tried {limit} anchors" in line[0]
    assert "is this the right map?" in line[0] and "Traceback" not in r.output
    assert len(calls) == limit  # bounded: that many registrations against the map, no more
    assert _snapshots(repo) == before and not (tmp_path / "w" / "publish").exists()


@pytest.mark.slow
def test_a_second_day_of_the_same_floor_anchors_at_once(floor_a, tmp_path):
    day2 = tmp_path / "day2"
    r = invoke("simulate", "floor", day2, "--world", floor_a["A"], "--changes", "5", "--illumination", "0.8",
               "--seed", "12", "--quiet")
    assert r.exit_code == 0, r.output
    repo = tmp_path / "map"
    shutil.copytree(floor_a["map"], repo)
    r = invoke("build", day2, "--map", repo, "-w", tmp_path / "w", "--report", tmp_path / "r.json", "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["publish"]["version"] == 2 and rep["geometry"]["frames_dropped"] == 0
    with open(tmp_path / "w" / "register" / "map_links.csv", newline="") as f:
        status = [row["status"] for row in csv.DictReader(f)]
    # its first attempt anchors: far from the limit that stops a log of another floor
    first = status.index("accepted")
    assert first < load_config()["register"]["map_max_failed_anchors"] // 4
