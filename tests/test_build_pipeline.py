"""End to end through the CLI: simulate a small floor, build it, check outputs and report keys."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import cli

REPORT_KEYS = (
    "links.candidates",
    "links.accepted",
    "links.rejected",
    "registration.pairs_per_s",
    "optimization.residual_rms_px",
    "optimization.seconds",
    "ground_truth.pose_rms_px",
    "ground_truth.pose_max_px",
    "ground_truth.link_error_median_px",
    "ground_truth.link_error_p95_px",
)


def get(report: dict, dotted: str):
    node = report
    for part in dotted.split("."):
        assert isinstance(node, dict) and part in node, f"report lacks {dotted!r}"
        node = node[part]
    return node


def invoke(*args: str):
    r = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    return r


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    log, work, report = root / "log", root / "w", root / "report.json"
    t0 = time.perf_counter()
    r = invoke("simulate", "floor", log, "--area", "1.5x1.5", "--seed", "3", "--quiet")
    assert r.exit_code == 0, r.output
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    r = invoke("build", log, "-w", work, "--report", report, "--quiet")
    t_build = time.perf_counter() - t0
    assert r.exit_code == 0, r.output
    return {"log": log, "work": work, "report": report, "output": r.output, "t_sim": t_sim, "t_build": t_build}


def test_small_floor_is_small(built):
    with open(built["log"] / "frames.csv") as f:
        n = sum(1 for _ in f) - 1
    assert 50 <= n <= 100, n
    assert built["t_sim"] < 15.0


def test_build_outputs_and_report(built):
    work = built["work"]
    assert (work / "poses.csv").is_file()
    assert (work / "links.csv").is_file()
    rep = json.loads(built["report"].read_text())
    for key in REPORT_KEYS:
        v = get(rep, key)
        assert v is not None and np.isfinite(v), (key, v)
    assert get(rep, "links.accepted") + get(rep, "links.rejected") == get(rep, "links.candidates")
    assert get(rep, "links.accepted") > 0
    assert get(rep, "registration.pairs_per_s") > 0
    assert get(rep, "ground_truth.pose_rms_px") < 0.5
    assert get(rep, "ground_truth.pose_max_px") >= get(rep, "ground_truth.pose_rms_px")
    assert get(rep, "ground_truth.link_error_p95_px") >= get(rep, "ground_truth.link_error_median_px")
    assert all(not rep["stages"][s]["skipped"] for s in ("ingest", "register", "optimize"))
    # each stage's CPU time beside its wall time (every thread of the build): register ran
    # on worker threads, so it used CPU; a stage's CPU can exceed its wall time on 2 cores
    assert all(rep["stages"][s]["cpu_seconds"] > 0 for s in ("ingest", "register", "optimize"))
    assert all(rep["stages"][s]["peak_rss_mb"] > 0 for s in ("ingest", "register", "optimize"))
    assert rep["stages"]["register"]["cpu_seconds"] < 2.5 * rep["stages"]["register"]["seconds"] + 1.0
    assert "optimize:" in built["output"]

    # poses.csv: one row per accepted frame, the drive log's pose columns first.
    with open(work / "poses.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[:4] == ["t", "x", "y", "theta"]
    assert len(rows) == rep["ingest"]["frames_accepted"] == get(rep, "optimization.frames")
    assert all(np.isfinite(float(r[k])) for r in rows for k in ("t", "x", "y", "theta"))
    # links.csv: every candidate, with residuals after optimization.
    with open(work / "links.csv", newline="") as f:
        links = list(csv.DictReader(f))
    assert len(links) == get(rep, "links.candidates")
    assert sum(r["status"] == "accepted" for r in links) == get(rep, "links.accepted")
    assert all(r["reason"] for r in links if r["status"] != "accepted")
    assert "residual_px" in links[0]


def test_plots_written(built):
    opt = built["work"] / "optimize"
    pngs = sorted(p.name for p in opt.glob("*.png"))
    assert any("traj" in n for n in pngs), pngs
    assert any("resid" in n for n in pngs), pngs
    for p in opt.glob("*.png"):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 1000


def test_rerun_skips_every_stage(built, tmp_path: Path):
    before = (built["work"] / "poses.csv").read_bytes()
    report = tmp_path / "rerun.json"
    r = invoke("build", built["log"], "-w", built["work"], "--report", report, "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads(report.read_text())
    assert set(rep["stages"]) == {"ingest", "register", "optimize"}
    assert all(s["skipped"] for s in rep["stages"].values()), rep["stages"]
    assert r.output.count("skipped") == 3
    # The skipped stages' figures still reach the report; outputs are unchanged.
    for key in REPORT_KEYS:
        get(rep, key)
    assert (built["work"] / "poses.csv").read_bytes() == before


def test_until_register_stops_there(built, tmp_path: Path):
    work = tmp_path / "w"
    report = tmp_path / "r.json"
    r = invoke("build", built["log"], "-w", work, "--until", "register", "--report", report, "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads(report.read_text())
    assert list(rep["stages"]) == ["ingest", "register"]
    assert (work / "register" / "links.csv").is_file()
    assert not (work / "optimize").exists()
    assert not (work / "poses.csv").exists()
    assert get(rep, "links.candidates") > 0
    assert "optimization" not in rep


def test_until_unknown_stage_is_usage_error(built, tmp_path: Path):
    r = CliRunner().invoke(cli, ["build", str(built["log"]), "-w", str(tmp_path / "w"), "--until", "paint"])
    assert r.exit_code == 2
    assert "--until" in r.output
