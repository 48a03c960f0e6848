"""The `orp` build stage (issue 7): coarse registration, a 2-run build, resume, publish, show.

Most tests write the horizon files alone (:func:`pipeline.omni_ingest.write_log_horizons`,
the contract's format without the floor ingest: faster); one builds through the real ingest.
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from pipeline.config import load_config
from pipeline.drivelog import read_drive_log
from pipeline.orp_register import coarse_register, roll_lines, signatures
from pipeline.stages.workspace import Workspace

SIM_CONFIG = """
[simulate.omni.motion]
frame_spacing_m = 0.04
"""


def write_horizons(log_dirs: list[Path], workdir: Path, cfg: dict, route_id: str | None = None) -> None:
    """``WORKDIR/ingest/horizons/<k:03d>.npz`` per log, as contract 2 of issue 7 says (the
    horizon lines alone, without the floor ingest: faster)."""
    from pipeline.omni_ingest import write_log_horizons

    for k, d in enumerate(log_dirs):
        write_log_horizons(read_drive_log(d), Workspace(workdir).horizons_file(k), cfg["tracker"]["orp"], route_id)


@pytest.fixture(scope="module")
def omni_logs(tmp_path_factory) -> list[Path]:
    """Three runs of a short loop (7 x 5 m room, frames every 4 cm), the later ones with --world."""
    d = tmp_path_factory.mktemp("omni")
    (d / "sim.toml").write_text(SIM_CONFIG)
    logs = [d / "a", d / "b", d / "c"]
    for out, extra in ((logs[0], ["--seed", "3", "--room", "7x5"]), (logs[1], ["--seed", "4", "--world", str(logs[0])]),
                       (logs[2], ["--seed", "5", "--world", str(logs[0])])):
        r = CliRunner().invoke(cli, ["simulate", "omni", str(out), "--quiet", "--config", str(d / "sim.toml"), *extra])
        assert r.exit_code == 0, r.output
    return logs


def test_coarse_registration_recovers_offset_and_heading():
    rng = np.random.default_rng(0)
    a = 360
    # a smooth random scene: lines that change along the path
    base = cv2.GaussianBlur(rng.uniform(30, 220, (400, a)).astype(np.float32), (0, 0), sigmaX=2.0, sigmaY=3.0)
    ref = base[50:350]
    lag_rows, heading_deg = 17, 23.4
    run = roll_lines(base[50 + lag_rows : 350 + lag_rows - 40], np.full(260, -math.radians(heading_deg)))
    run = 1.3 * np.clip(run, 1, 255) + 5.0  # another exposure
    c = coarse_register(signatures(ref), signatures(run), a, 0.1, 3.0)
    assert abs(c.offset_m - lag_rows * 0.1) < 1e-6
    assert abs(math.degrees(c.dtheta) - heading_deg) < 0.1
    assert c.ncc > 0.9


def test_orp_stage_two_runs_recovers_poses(omni_logs, tmp_path):
    from pipeline.stages.orp import STAGE, read_route_file, run_orp

    cfg = load_config(None)
    write_horizons(omni_logs[:2], tmp_path, cfg, route_id="loop")
    out = tmp_path / "orp"
    out.mkdir()
    rep = run_orp(Workspace(tmp_path).writing("orp", out), STAGE.params(cfg))["orp"]
    assert rep["runs"] == 2 and len(rep["routes"]) == 1
    reg = rep["registration"]
    assert reg["fixes_accepted"] >= 0.8 * reg["fixes_tried"] > 0
    gt = rep["ground_truth"]
    assert gt["pose_rms_m"] < 0.03 and gt["heading_rms_deg"] < 1.0
    rec, fig = read_route_file(out / "loop.npz")
    assert rec.lines.dtype == np.uint8 and rec.spacing_m == cfg["orp"]["spacing_m"]
    assert fig["rows_fed"]["b"] > 0.5 * rec.rows
    # route poses against the first run's truth
    truth = np.loadtxt(omni_logs[0] / "ground_truth.csv", delimiter=",", skiprows=1)
    assert abs(rec.length_m - np.sum(np.hypot(*np.diff(truth[:, 1:3], axis=0).T))) < 0.2


def _fake_ingest(monkeypatch, cfg):
    """The horizon files written by the fixture instead of ingest (whose bird's-eye floor
    frames cost more than this test needs; the bench runs the real ingest)."""
    import pipeline.stages.build as build

    def fake(ws, params):
        tmpw = ws.root / "_h"
        write_horizons([lg.path for lg in params.build.logs], tmpw, params.cfg, route_id="loop")
        os.replace(Workspace(tmpw).horizons_dir, ws.horizons_dir)
        return {"ingest": {"frames_total": 0}}

    monkeypatch.setitem(build.STAGES, "ingest", replace(build.STAGES["ingest"], run=fake))


def test_build_resume_publish_show(omni_logs, tmp_path, monkeypatch):
    from pipeline.stages.build import run_build

    cfg = load_config(None)
    cfg["build"]["stages"] = ["ingest", "publish"]  # the floor stages need OMNI-INGEST's bird's-eye frames
    _fake_ingest(monkeypatch, cfg)
    work, repo = tmp_path / "w", tmp_path / "map"
    two = omni_logs[:2]
    rep = run_build(two, work, cfg, until="orp", quiet=True)
    assert set(rep["stages"]) == {"ingest", "orp"} and not rep["stages"]["orp"]["skipped"]
    assert (work / "orp" / "loop.npz").is_file() and rep["orp"]["routes"][0]["id"] == "loop"
    assert sorted(p.name for p in (work / "orp").iterdir()) == ["loop.npz", "manifest.json", "runs.csv"]  # as declared
    rep2 = run_build(two, work, cfg, quiet=True, map_url=str(repo))
    assert rep2["stages"]["orp"]["skipped"] and rep2["orp"]["rows"] == rep["orp"]["rows"]
    assert rep2["publish"]["routes_written"] == 1
    import zarr

    from mapstore.repository import MapRepository
    from mapstore.routes import list_routes, read_route

    mrepo = MapRepository.open(str(repo))
    assert len(mrepo.log()) == 2  # the initial commit and one publish
    root = zarr.open_group(mrepo.readonly().store, mode="r")
    assert list_routes(root) == ["loop"]
    rec = read_route(root, "loop")
    assert rec.version == 1 and [s["log_id"] for s in rec.sources] == ["a", "b"]
    assert rec.rows == rep["orp"]["rows"]
    r = CliRunner().invoke(cli, ["show", str(repo)])
    assert r.exit_code == 0, r.output
    assert "loop" in r.output and "routes" in r.output
    png = tmp_path / "q.png"
    r = CliRunner().invoke(cli, ["quicklook", str(repo), "--route", "loop", "--out", str(png)])
    assert r.exit_code == 0, r.output
    img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert img.shape[0] == rec.rows

    # a later build over the published route: the new run is localized on the stored route
    # (its poses fixed), averaged in, and the route refreshed as version 2
    rep3 = run_build(omni_logs[2:], tmp_path / "w2", cfg, quiet=True, map_url=str(repo))
    route = rep3["orp"]["routes"][0]
    assert route["refreshed"] and route["registration"]["reference"] == "stored route"
    assert route["registration"]["fixes_accepted"] >= 0.8 * route["registration"]["fixes_tried"] > 0
    assert route["rows_fed"]["c"] > 0.5 * rec.rows and route["ground_truth"]["pose_rms_m"] < 0.03
    root = zarr.open_group(MapRepository.open(str(repo)).readonly().store, mode="r")
    rec2 = read_route(root, "loop")
    assert rec2.version == 2 and [(s["log_id"], s["version"]) for s in rec2.sources] == [("a", 1), ("b", 1), ("c", 2)]
    np.testing.assert_array_equal(rec2.poses, rec.poses)  # the stored geometry is kept
    assert rec2.meta["runs"] == 3
    # a log already merged into the route: refused; the same build again: already published
    from pipeline.errors import BadInput

    with pytest.raises(BadInput, match="already in the map"):
        run_build(omni_logs[1:2], tmp_path / "w3", cfg, quiet=True, map_url=str(repo))
    rep4 = run_build(omni_logs[2:], tmp_path / "w2", cfg, quiet=True, map_url=str(repo))
    assert all(v["skipped"] for v in rep4["stages"].values())


def test_orp_stage_only_with_omni_logs():
    from types import SimpleNamespace

    from pipeline.stages.build import _with_orp

    def lg(omni: bool):
        return SimpleNamespace(camera=SimpleNamespace(is_omni=omni))

    stages = ["ingest", "register", "optimize", "render", "publish"]
    assert _with_orp(stages, [lg(False)]) == stages
    assert _with_orp(stages, [lg(False), lg(True)], floor_poses=False) == ["ingest", "orp", *stages[1:]]
    assert _with_orp(["ingest", "orp", "publish"], [lg(False)]) == ["ingest", "publish"]
    assert _with_orp(stages, [lg(True)], floor_poses=True) == ["ingest", "register", "optimize", "orp", "render",
                                                               "publish"]
    assert _with_orp(["ingest", "publish"], [lg(True)], floor_poses=True) == ["ingest", "orp", "publish"]


def test_build_with_ingest_horizons(omni_logs, tmp_path):
    """The real ingest (bird's-eye floor frames and horizon files) feeds the orp stage; the
    floor stages are left out here (routes only)."""
    from pipeline.stages.build import run_build

    cfg = load_config(None)
    cfg["build"]["stages"] = ["ingest", "publish"]
    rep = run_build(omni_logs[:2], tmp_path / "w", cfg, quiet=True, map_url=str(tmp_path / "map"))
    assert list(rep["stages"]) == ["ingest", "orp", "publish"]
    route = rep["orp"]["routes"][0]
    assert route["runs"] == 2 and route["registration"]["fixes_accepted"] > 0
    assert rep["orp"]["ground_truth"]["pose_rms_m"] < 0.03
    assert rep["publish"]["routes_written"] == 1


def _stretch(run, s_lo: float, s_hi: float):
    """A run cut to the frames whose odometry path length lies in [s_lo, s_hi] (metres)."""
    from pipeline.stages.orp import Run
    from tracker.orp import path_length

    s = path_length(run.odometry)
    sel = (s >= s_lo) & (s <= s_hi)
    return Run(run.k, run.lines[sel], run.t[sel], run.frame[sel], run.odometry[sel], dict(run.meta))


def _check_continuous(rec, spacing: float) -> None:
    steps = np.hypot(*np.diff(rec.poses[:, :2].astype(float), axis=0).T)
    turns = np.degrees(np.abs(np.diff(np.unwrap(rec.poses[:, 2].astype(float)))))
    assert steps.max() < spacing + 0.03 and np.median(steps) == pytest.approx(spacing, abs=0.002)
    # the loop's corners (radius 1 m) turn spacing / 1 m per row; a junction adds at most 2 deg
    assert turns.max() < np.degrees(spacing / 1.0) + 2.0


def test_route_extension_refresh_and_first_build(omni_logs, tmp_path):
    """A short stored route (1..6 m of run a) refreshed with the whole run b grows at both
    ends, its old rows unchanged within noise, its poses continuous; a first build of the
    short run and the whole run c covers the union too."""
    from pipeline.stages.orp import build_route, read_runs

    cfg = load_config(None)
    write_horizons(omni_logs, tmp_path, cfg, route_id="loop")
    a, b, c = read_runs(Workspace(tmp_path))
    h = cfg["orp"]["spacing_m"]
    truth = np.loadtxt(omni_logs[1] / "ground_truth.csv", delimiter=",", skiprows=1)
    loop_m = float(np.sum(np.hypot(*np.diff(truth[:, 1:3], axis=0).T)))
    short = build_route("loop", [_stretch(a, 1.0, 6.0)], cfg)["record"]
    assert short.s0_m == 0.0 and abs(short.length_m - 5.0) < 0.1
    out = build_route("loop", [b], cfg, stored=short)
    rec, fig = out["record"], out["figures"]
    ext = fig["extended_m"]
    assert abs(ext["start"] - 1.0) < 0.3 and abs(ext["start"] + short.length_m + ext["end"] - loop_m) < 0.5
    assert {x["side"] for x in fig["extensions"]} == {"start", "end"}
    assert all(x["log_id"] == "b" and x["gap_m"] < 0.05 for x in fig["extensions"])
    assert rec.s0_m == pytest.approx(-ext["start"]) and rec.rows == short.rows + round(sum(ext.values()) / h)
    i0 = round((short.s0_m - rec.s0_m) / h)
    np.testing.assert_array_equal(rec.poses[i0:i0 + short.rows], short.poses)  # stored rows stay put
    old = rec.lines[i0:i0 + short.rows].astype(float) - short.lines
    assert np.abs(old).mean() < 4.0  # averaged with run b: noise only
    _check_continuous(rec, h)
    assert fig["ground_truth"]["pose_rms_m"] < 0.03
    # a first build: the short run is the reference, run c extends it at both ends
    first = build_route("loop", [_stretch(a, 1.0, 6.0), c], cfg)
    rec1, fig1 = first["record"], first["figures"]
    assert rec1.s0_m == 0.0 and fig1["extended_m"]["start"] > 0.7 and fig1["extended_m"]["end"] > loop_m - 6.5
    assert abs(rec1.length_m - loop_m) < 0.6
    _check_continuous(rec1, h)


@pytest.fixture(scope="module")
def omni_runs(omni_logs, tmp_path_factory):
    """The fixture logs' runs (:func:`pipeline.stages.orp.read_runs`), horizon files written once."""
    from pipeline.stages.orp import read_runs

    w = tmp_path_factory.mktemp("runs")
    write_horizons(omni_logs, w, load_config(None), route_id="loop")
    return read_runs(Workspace(w))


def test_refresh_keeps_stored_spacing(omni_runs):
    """A route stored at 2 cm refreshed with the default (10 cm) config stays at 2 cm: rows
    2 cm apart along its poses, path lengths rows x 2 cm; a sampling mismatch is BadInput."""
    import copy

    from pipeline.errors import BadInput
    from pipeline.stages.orp import build_route

    a, b, _ = omni_runs
    cfg = load_config(None)
    assert cfg["orp"]["spacing_m"] == pytest.approx(0.10)
    fine = copy.deepcopy(cfg)
    fine["orp"]["spacing_m"] = 0.02
    short = build_route("loop", [_stretch(a, 1.0, 4.0)], fine)["record"]
    assert short.spacing_m == pytest.approx(0.02) and abs(short.length_m - 3.0) < 0.1
    out = build_route("loop", [_stretch(b, 0.0, 5.0)], cfg, stored=short)
    rec, fig = out["record"], out["figures"]
    assert rec.spacing_m == pytest.approx(0.02) and out["figures"]["length_m"] == pytest.approx(rec.length_m)
    assert rec.length_m == pytest.approx(0.02 * (rec.rows - 1))
    assert fig["extended_m"]["start"] > 0.5 and fig["extended_m"]["end"] > 0.5
    i0 = round((short.s0_m - rec.s0_m) / 0.02)
    assert rec.s0_m == pytest.approx(-fig["extended_m"]["start"])
    np.testing.assert_array_equal(rec.poses[i0:i0 + short.rows], short.poses)
    _check_continuous(rec, 0.02)  # prepended and appended rows 2 cm apart too
    assert fig["rows_fed"]["b"] > 0.5 * short.rows
    bad = copy.deepcopy(short)
    bad.horizon_band_deg = short.horizon_band_deg + 1.0
    with pytest.raises(BadInput, match=r"\[tracker.orp\] horizon_band_deg: the stored route has"):
        build_route("loop", [_stretch(b, 0.0, 5.0)], cfg, stored=bad)


def test_sparse_frames_interpolated(omni_runs, caplog):
    """Frames 15-16 cm apart (1.5 m/s at 10 Hz) with merge_max_gap_m = 10 cm: no row is left
    black; they are the reference's lines interpolated across the gaps, counted and warned."""
    import logging

    from pipeline.orp_register import keep_every
    from pipeline.stages.orp import Run, build_route
    from tracker.orp import build_orp, path_length

    a = _stretch(omni_runs[0], 0.0, 5.0)
    sel = keep_every(path_length(a.odometry), 0.15)
    sparse = Run(a.k, a.lines[sel], a.t[sel], a.frame[sel], a.odometry[sel], dict(a.meta))
    assert np.median(np.diff(path_length(sparse.odometry))) >= 0.15
    cfg = load_config(None)
    with caplog.at_level(logging.WARNING, logger="pipeline.stages.orp"):
        out = build_route("loop", [sparse], cfg)
    rec, fig = out["record"], out["figures"]
    assert fig["rows_interpolated"] > 0.5 * rec.rows and "interpolated" in caplog.text
    assert rec.lines.mean(1).min() > 20  # no black rows
    want = build_orp(sparse.lines, sparse.odometry, cfg["orp"]["spacing_m"], rec.samples_per_degree).lines
    n = min(len(want), rec.rows)
    assert np.abs(rec.lines[:n].astype(int) - want[:n]).max() <= 2


def test_short_runs(omni_runs):
    """A reference run that barely moves: BadInput naming the log; another run that short:
    skipped with a warning and counted."""
    from pipeline.errors import BadInput
    from pipeline.stages.orp import build_route

    a, b, _ = omni_runs
    cfg = load_config(None)
    tiny = _stretch(b, 0.0, 0.12)
    with pytest.raises(BadInput, match="too short for a route panorama"):
        build_route("loop", [tiny, _stretch(a, 0.0, 3.0)], cfg)
    out = build_route("loop", [_stretch(a, 0.0, 3.0), tiny], cfg)
    assert [x["log_id"] for x in out["figures"]["skipped"]] == ["b"] and out["figures"]["runs"] == 1


def test_floor_priors_digit_log_ids(tmp_path):
    """A log id of digits ("001", kept as text) finds its floor poses in optimize/poses.csv."""
    from pipeline.stages.orp import Run, floor_priors

    n = 5
    odo = np.column_stack([np.arange(n) * 0.1, np.zeros(n), np.zeros(n)])
    run = Run(0, np.zeros((n, 360), np.float32), np.arange(n) * 0.1, np.arange(n), odo.copy(), {"log_id": "001"})
    (tmp_path / "optimize").mkdir()
    rows = ["t,x,y,theta,log_id,frame"] + [f"{0.1 * i!r},{0.1 * i + 1.0!r},2.0,0.0,001,{i}" for i in range(n)]
    (tmp_path / "optimize" / "poses.csv").write_text("\n".join(rows) + "\n")
    assert floor_priors(Workspace(tmp_path), [run]) == 1
    np.testing.assert_allclose(run.odometry[:, 0], odo[:, 0] + 1.0)
    np.testing.assert_allclose(run.odometry[:, 1], 2.0)
    assert run.dead_reckoning is not None


def test_publish_routes_only_of_this_build(tmp_path):
    """Route files of an earlier build in a reused workdir are not published unless the orp
    stage is part of this build."""
    from pipeline.stages.publish import build_routes

    (tmp_path / "orp").mkdir()
    (tmp_path / "orp" / "loop.npz").write_bytes(b"")
    assert build_routes(Workspace(tmp_path), {"stages": {"ingest": {}, "orp": {"skipped": True}}}) == {
        "loop": tmp_path / "orp" / "loop.npz"}
    assert build_routes(Workspace(tmp_path), {"stages": {"ingest": {}, "register": {}}}) == {}
