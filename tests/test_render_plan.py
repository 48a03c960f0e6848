"""Where the render runs (pipeline.stages.render.render_plan): ``[render] scheduler = "auto"``
picks worker processes for a large map and threads for a small one."""

from __future__ import annotations

import pytest

from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.stages.render import render_plan

PX = 0.0025


def _rcfg(**over) -> dict:
    rcfg = dict(load_config(None)["render"])
    rcfg.update(over)
    return rcfg


def _grid(mpix: float) -> MapGrid:
    side = int((mpix * 1e6) ** 0.5) + 1
    return MapGrid(0.0, side * PX, PX, side, side)


def test_the_default_is_auto_with_a_documented_threshold():
    rcfg = _rcfg()
    assert rcfg["scheduler"] == "auto" and rcfg["processes_min_mpix"] > 0


@pytest.mark.parametrize("cores", [2, 8])
def test_auto_runs_a_large_map_on_a_process_per_core_and_a_small_one_on_threads(monkeypatch, cores):
    monkeypatch.setattr("os.cpu_count", lambda: cores)
    rcfg = _rcfg(processes_min_mpix=100.0)
    assert render_plan(rcfg, _grid(100.0)) == ("processes", cores)
    assert render_plan(rcfg, _grid(20.0)) == ("threads", cores)
    # one worker: no process to start
    assert render_plan(_rcfg(processes_min_mpix=100.0, workers=1), _grid(300.0)) == ("threads", 1)


def test_a_named_scheduler_is_used_as_named(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    for name in ("threads", "processes", "sync", "tcp://127.0.0.1:8786"):
        assert render_plan(_rcfg(scheduler=name), _grid(1.0)) == (name, 4)
        assert render_plan(_rcfg(scheduler=name, workers=3), _grid(500.0)) == (name, 3)
