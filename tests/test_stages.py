"""The stage protocol: ``run(ws, params) -> report sections``, each stage given only the
configuration tables it declares, its cache fingerprint derived from that declaration and
the files it writes, every path through the work directory's :class:`Workspace`."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from pipeline.stages import build
from pipeline.config import load_config
from pipeline.stages.stage import BuildContext, Stage, config_tables, declared_tables
from pipeline.stages.workspace import OUTPUTS, Workspace

FLOOR = ("ingest", "register", "optimize")


def test_every_stage_is_declared_once_in_build_order():
    assert list(build.STAGES) == ["ingest", "orp", "register", "optimize", "render", "publish"]
    for name, stage in build.STAGES.items():
        assert isinstance(stage, Stage) and stage.name == name
        assert stage.params_tables and stage.outputs == OUTPUTS[name]
    assert build.MAP_STAGES == ("render", "publish") and build.SIDE_STAGES == ("orp",)


def test_a_stage_is_given_its_declared_tables_and_nothing_else():
    cfg = load_config(None)
    for stage in build.STAGES.values():
        params = stage.params(cfg, BuildContext())
        assert set(params.cfg) == {t.split(".")[0] for t in stage.params_tables}, stage.name
        assert config_tables(params.cfg, stage.params_tables) == config_tables(cfg, stage.params_tables)
    orp = build.STAGES["orp"].params(cfg).cfg
    assert orp["tracker"] == {"orp": cfg["tracker"]["orp"]} and "publish" not in orp
    with pytest.raises(KeyError):
        build.STAGES["register"].params(cfg).cfg["render"]  # undeclared: not there to go stale
    assert declared_tables(cfg, ("map", "tracker.orp")) == {"map": cfg["map"], "tracker": {"orp": cfg["tracker"]["orp"]}}


def test_the_workspace_resolves_the_writing_stage_into_its_temporary_directory(tmp_path):
    ws = Workspace(Path("w"))
    assert ws.poses == Path("w/optimize/poses.csv") and ws.frames_store == Path("w/ingest/frames.zarr")
    assert ws.register_links == Path("w/register/links.csv") and ws.touched == Path("w/render/touched.json")
    opt = ws.writing("optimize", tmp_path / ".tmp-optimize-1")
    assert opt.poses == tmp_path / ".tmp-optimize-1" / "poses.csv"  # its own output
    assert opt.register_links == Path("w/register/links.csv")  # another stage's: finished
    assert opt.manifest("optimize") == tmp_path / ".tmp-optimize-1" / "manifest.json"
    assert opt.result_poses == Path("w/poses.csv")
    assert Workspace(Path()).horizons_file(2) == Path("ingest/horizons/002.npz")  # as the report names it


def _recording_stages(monkeypatch, ran: list) -> None:
    """The floor stages replaced by recorders that keep their real declarations (tables,
    outputs): what the cache decides is derived from those alone."""
    for name in FLOOR:
        def fn(ws, params, name=name):
            ran.append(name)
            return {name: {"tables": sorted(params.cfg)}}
        monkeypatch.setitem(build.STAGES, name, replace(build.STAGES[name], run=fn, after=None))


def test_changing_a_knob_reruns_exactly_the_stages_that_read_its_table(small_log, tmp_path, monkeypatch):
    ran: list = []
    _recording_stages(monkeypatch, ran)
    cfg = load_config(None)
    cfg["build"]["stages"] = list(FLOOR)
    work = tmp_path / "w"

    def rerun(**knobs) -> list:
        for dotted, value in knobs.items():
            table, key = dotted.split("__")
            cfg[table][key] = value
        ran.clear()
        rep = build.run_build([small_log], work, cfg, quiet=True)
        assert [n for n in FLOOR if not rep["stages"][n]["skipped"]] == ran
        return list(ran)

    assert rerun() == list(FLOOR)
    assert rerun() == []  # the same input: every stage re-used
    assert rerun(render__feather_px=12.0, publish__max_residual_px=4.0) == []  # no floor stage reads these
    assert rerun(optimize__odometry_sigma_floor_m=0.001) == ["register", "optimize"]  # both declare [optimize]
    assert rerun(register__min_predicted_overlap=0.03) == ["register", "optimize"]  # optimize: its upstream moved
    assert rerun(ingest__max_bad_fraction=0.05) == list(FLOOR)
    # how the work runs is not what it computes: another scheduler or worker count re-uses all
    assert rerun(register__scheduler="sync", register__workers=1, render__workers=1, ingest__workers=1) == []
    assert rerun() == []


def test_renaming_a_declared_output_reruns_its_stage(small_log, tmp_path, monkeypatch):
    ran: list = []
    _recording_stages(monkeypatch, ran)
    cfg = load_config(None)
    cfg["build"]["stages"] = list(FLOOR)
    build.run_build([small_log], tmp_path / "w", cfg, quiet=True)
    monkeypatch.setitem(OUTPUTS, "register", tuple(n.replace("links.csv", "links2.csv") for n in OUTPUTS["register"]))
    ran.clear()
    build.run_build([small_log], tmp_path / "w", cfg, quiet=True)
    assert ran == ["register", "optimize"]
