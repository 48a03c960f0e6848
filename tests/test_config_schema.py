"""The configuration's schema (pipeline/schema*.py, mapstore/knobs.py): every table of
configs/*.toml has a frozen dataclass giving each key's type and range, the shipped defaults
pass it unchanged, and a bad user file is refused at load time with one line naming the file,
the table, the key and what is allowed (exit code 2)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

import pipeline.config as config
from mapstore.knobs import ConfigError, from_table, knob
from pipeline import schema, schema_diff, schema_export, schema_floor, schema_omni, schema_simulate
from pipeline.cli import cli
from pipeline.config import config_hash, default_config, load_config
from pipeline.errors import BadInput

REPO = Path(__file__).resolve().parents[1]


def _table(cfg: dict, name: str) -> dict:
    for part in name.split("."):
        cfg = cfg[part]
    return cfg


def _toml_tables(cfg: dict, prefix: str = "") -> dict[str, set[str]]:
    """Every table of a configuration that holds values -> its value keys."""
    out = {}
    scalars = {k for k, v in cfg.items() if not isinstance(v, dict)}
    if prefix and scalars:
        out[prefix] = scalars
    for k, v in cfg.items():
        if isinstance(v, dict):
            out.update(_toml_tables(v, f"{prefix}.{k}" if prefix else k))
    return out


# --- the schema against the shipped defaults -------------------------------------------------


def test_every_dataclass_field_is_a_toml_key_and_back():
    tables = _toml_tables(default_config())
    assert set(tables) == set(schema.TABLES)
    for name, cls in schema.TABLES.items():
        fields = {f.name for f in dataclasses.fields(cls)}
        assert fields == tables[name], (name, fields ^ tables[name])


def test_the_shipped_defaults_pass_unchanged():
    raw = default_config()
    checked = load_config(None)
    # same values of the same types (an int stays an int, a float a float): stage
    # fingerprints and everything built from the configuration are as before
    assert json.dumps(checked, sort_keys=True) == json.dumps(raw, sort_keys=True)
    assert config_hash(checked) == config_hash(raw)
    for name in schema.TABLES:
        schema.check_table(name, _table(checked, name))


def test_pipeline_tables_carry_no_defaults():
    """The defaults live in configs/*.toml only: the pipeline's schema dataclasses give types
    and ranges (the tracker's settings and mapstore's RouteDiffParams / BundleLimits keep
    theirs as a library API, checked equal to the TOML below)."""
    for mod in (schema_floor, schema_diff, schema_export, schema_omni, schema_simulate):
        for cls in {c for c in schema.TABLES.values() if c.__module__ == mod.__name__}:
            for f in dataclasses.fields(cls):
                assert f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING, (cls, f.name)


def test_dataclass_defaults_equal_the_toml():
    cfg = load_config(None)
    for name, cls in schema.TABLES.items():
        fields = dataclasses.fields(cls)
        if all(f.default is not dataclasses.MISSING for f in fields):
            assert schema.check_table(name, _table(cfg, name)) == cls(), name


# --- a user file ---------------------------------------------------------------------------------


def _user(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "user.toml"
    p.write_text(text)
    return p


def _refused(tmp_path: Path, text: str) -> str:
    """The one-line error of `mosaicmap config show --config FILE` (asserting exit code 2)."""
    user = _user(tmp_path, text)
    r = CliRunner().invoke(cli, ["config", "show", "--config", str(user)])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.output, r.output
    assert lines[0].startswith(f"mosaicmap: error: {user}: "), lines[0]
    return lines[0]


def test_a_negative_revisit_window_is_refused(tmp_path):
    line = _refused(tmp_path, "[register]\nrevisit_window_m = -3.0\n")
    assert line.endswith("[register] revisit_window_m: -3.0 is out of range; allowed: x >= 0")


def test_a_bad_value_stops_a_build_before_it_reads_anything(tmp_path):
    user = _user(tmp_path, "[register]\nrevisit_window_m = -3\n")
    r = CliRunner().invoke(cli, ["build", str(tmp_path / "no-such-log"), "--workdir", str(tmp_path / "w"),
                                 "--config", str(user), "--quiet"])
    assert r.exit_code == 2
    assert r.output.strip() == f"mosaicmap: error: {user}: [register] revisit_window_m: -3 is out of range; allowed: x >= 0"
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("text, tail", [
    # out of range
    ("[optimize]\nmax_iterations = 0\n", "[optimize] max_iterations: 0 is out of range; allowed: x >= 1"),
    ("[ingest]\nmax_bad_fraction = 1.5\n", "[ingest] max_bad_fraction: 1.5 is out of range; allowed: 0 <= x <= 1"),
    ("[tracker.floor]\nsearch_sigmas = 0.0\n", "[tracker.floor] search_sigmas: 0.0 is out of range; allowed: x > 0"),
    ("[diff.routes]\nsector_min_row_fraction = -0.1\n",
     "[diff.routes] sector_min_row_fraction: -0.1 is out of range; allowed: 0 <= x <= 1"),
    ("[simulate.omni.camera]\nframe_size = [640, 0]\n",
     "[simulate.omni.camera] frame_size: 0 is out of range; allowed: x >= 1"),
    ("[map]\nzstd_level = 30\n", "[map] zstd_level: 30 is out of range; allowed: 1 <= x <= 22"),
    ("[ingest.photometry]\ntarget_levels = [200.0, 20.0]\n",
     "[ingest.photometry] target_levels: [200.0, 20.0] must not decrease ([low, high])"),
    ("[optimize]\nrobust_anneal_k = [10.0, 30.0]\n",
     "[optimize] robust_anneal_k: [10.0, 30.0] must decrease strictly"),
    # choices
    ("[render]\nscheduler = \"thread\"\n",
     '[render] scheduler: "thread" is not allowed; allowed: one of "threads", "processes", "sync", "auto", '
     'SCHEME://ADDRESS (SCHEME: tcp, tls, inproc, ucx, ws, wss)'),
    ("[export]\nlayers = [\"intensity\", \"texure\"]\n",
     '[export] layers: "texure" is not allowed; allowed: one of "intensity", "coverage", "texture", '
     '"uniqueness", "updated"'),
    ("[simulate.tiles]\nbits = 12\n", "[simulate.tiles] bits: 12 is not allowed; allowed: one of 8, 16"),
    # wrong type
    ("[register]\nworkers = 1.5\n", "[register] workers: must be an integer, got a number 1.5"),
    ("[diff]\nblur_sigma_px = \"2\"\n", '[diff] blur_sigma_px: must be a number, got a string "2"'),
    ("[tracker.session]\nrelative = 1\n", "[tracker.session] relative: must be true or false, got an integer"),
    ("[orp]\nfloor_poses = \"yes\"\n", "[orp] floor_poses: must be true or false, got a string"),
    ("[tracker.floor]\ngrid_cells = [3, 4, 5]\n", "[tracker.floor] grid_cells: must be a list of 2 integers, got 3 values"),
    ("[map]\nsite_extent_m = [0.0, 0.0, 1.0]\n", "[map] site_extent_m: must hold 0 or 4 values, got 3"),
    # unknown key or table
    ("[register]\nrevisit_windw_m = 3.0\n", '[register] revisit_windw_m: unknown key (did you mean "revisit_window_m"?)'),
    ("[tracker.floor]\nn_templats = 3\n", '[tracker.floor] n_templats: unknown key (did you mean "n_templates"?)'),
    ("[tracker.flor]\nn_templates = 3\n", '[tracker] flor: unknown table (did you mean "floor"?)'),
    ("[omni]\nouter_radius_m = {x = 1}\n", "[omni] outer_radius_m: must be a value, not a table"),
])
def test_a_bad_user_file_is_one_line_naming_file_table_key(tmp_path, text, tail):
    assert _refused(tmp_path, text).endswith(": " + tail)


def test_zero_stays_allowed_where_it_means_off_or_automatic(tmp_path):
    user = _user(tmp_path, """
[map]
pixel_size_m = 0.0
[render]
coverage_depth = 0
frame_step_fraction = 0.0
workers = 0
[optimize]
jump_speed_factor = 0.0
odometry_gate_sigmas = 0.0
robust_anneal_k = []
[register]
revisit_window_m = 0.0
coarse_window_px = 0
peak_null_pairs = 0
map_max_failed_anchors = 0
fine_background_px = 0.0
[ingest.quality]
hot_pixel_sigmas = 0.0
[tracker.floor]
refine_radius_px = 0
prefilter_noise = 0.0
[tracker.orp]
highpass_deg = 0.0
normalize_deg = 0.0
[orp]
stored_weight = 0.0
[export]
route_rows_per_chunk = 0
levels = []
[simulate.floor]
changes = 0
height_jitter = 0.0
""")
    cfg = load_config(user)
    assert cfg["register"]["revisit_window_m"] == 0.0 and cfg["optimize"]["jump_speed_factor"] == 0.0


def test_a_dask_scheduler_address_is_allowed(tmp_path):
    cfg = load_config(_user(tmp_path, '[register]\nscheduler = "tcp://10.0.0.5:8786"\n'))
    assert cfg["register"]["scheduler"] == "tcp://10.0.0.5:8786"
    for bad in ("tcp://", "http://host:8786", "tcp://host :8786"):
        assert "[register] scheduler" in _refused(tmp_path, f'[register]\nscheduler = "{bad}"\n')


def test_a_command_line_override_is_checked_too(tmp_path, small_log):
    """`build --scheduler` sets the configuration after it was loaded: run_build checks it."""
    r = CliRunner().invoke(cli, ["build", str(small_log), "-w", str(tmp_path / "w"), "--scheduler", "thread", "-q"])
    assert r.exit_code == 2, r.output
    assert r.output.startswith("mosaicmap: error: configuration (after command-line options): ["), r.output
    assert '] scheduler: "thread" is not allowed; allowed: one of "threads"' in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_an_integer_for_a_number_becomes_a_float(tmp_path):
    cfg = load_config(_user(tmp_path, "[register]\nrevisit_window_m = 5\n[tracker.orp]\nsmoothing_deg = [4, 2]\n"
                                      "iterations = [6, 4]\n"))
    assert cfg["register"]["revisit_window_m"] == 5.0 and isinstance(cfg["register"]["revisit_window_m"], float)
    assert cfg["tracker"]["orp"]["smoothing_deg"] == [4.0, 2.0]
    assert all(isinstance(v, float) for v in cfg["tracker"]["orp"]["smoothing_deg"])
    assert cfg["tracker"]["orp"]["iterations"] == [6, 4]


def test_a_broken_default_names_its_own_file(monkeypatch, tmp_path):
    for p in (REPO / "configs").glob("*.toml"):
        shutil.copy(p, tmp_path / p.name)
    floor = tmp_path / "floor.toml"
    floor.write_text(floor.read_text().replace("revisit_window_m = 3.0", "revisit_window_m = -3.0"))
    monkeypatch.setattr(config, "CONFIG_DIR", tmp_path)
    with pytest.raises(BadInput) as e:
        load_config(None)
    assert e.value.where == str(floor)
    assert e.value.what == "[register] revisit_window_m: -3.0 is out of range; allowed: x >= 0"
    # a key the schema does not know, in a default file
    floor.write_text(floor.read_text().replace("revisit_window_m = -3.0", "revisit_window_m = 3.0\nbogus_knob = 1"))
    with pytest.raises(BadInput, match=r"\[register\] bogus_knob: unknown key") as e:
        load_config(None)
    assert e.value.where == str(floor)


def test_a_user_value_overriding_a_good_default_names_the_user_file(tmp_path):
    user = _user(tmp_path, "[tracker.reloc]\nratio = 1.5\n")
    with pytest.raises(BadInput) as e:
        load_config(user)
    assert e.value.where == str(user)
    assert e.value.what == "[tracker.reloc] ratio: 1.5 is out of range; allowed: 0 < x <= 1"


# --- the readers built on it -----------------------------------------------------------------------


def test_settings_give_typed_tables():
    cfg = load_config(None)
    reg = schema.settings(schema_floor.RegisterConfig, cfg["register"])
    assert reg.revisit_window_m == cfg["register"]["revisit_window_m"] and reg.progressive_revisits is True
    ing = schema.settings(schema_floor.IngestConfig, cfg["ingest"])  # its sub-tables are theirs
    assert ing.on_bad_image == cfg["ingest"]["on_bad_image"]
    odo = schema.settings(schema_simulate.SimOdometryConfig, cfg["simulate"]["omni"]["odometry"],
                          "simulate.omni.odometry")
    assert odo.frame == "world"
    with pytest.raises(ConfigError, match=r"\[optimize\] anchor_sigma_m: missing"):
        schema.settings(schema_floor.OptimizeConfig, {k: v for k, v in cfg["optimize"].items() if k != "anchor_sigma_m"})


def test_the_readers_of_tables_use_the_schema():
    from pipeline.geometry_gate import JumpParams
    from pipeline.optimize import pose_model
    from pipeline.prior_bias import BiasParams
    from pipeline.registration import RegistrationParams

    cfg = load_config(None)
    reg, opt = cfg["register"], cfg["optimize"]
    p = RegistrationParams.from_config(reg)
    assert p.min_overlap_fraction == reg["min_overlap_fraction"] and p.coarse.window_px == reg["coarse_window_px"]
    assert p.coarse.min_overlap_px == p.min_overlap_px == reg["min_overlap_px"]
    assert BiasParams.from_config(reg).min_scale_links == reg["prior_min_scale_links"]
    assert JumpParams.from_config(opt).max_frames == opt["jump_max_frames"]
    assert pose_model({**opt, "pose_model": "Similarity2"}) == "similarity2"
    # a table missing a key is refused (no hidden default in the code)
    for reader, table in ((RegistrationParams.from_config, reg), (JumpParams.from_config, opt)):
        key = next(iter(table))
        with pytest.raises(ConfigError, match="missing"):
            reader({k: v for k, v in table.items() if k != key})


def test_tracker_settings_from_a_partial_table_are_strict():
    from tracker.floor import FloorTrackerParams
    from tracker.orp_reloc import ORPRelocParams

    assert FloorTrackerParams.from_dict({"n_templates": 6}).n_templates == 6
    with pytest.raises(ValueError, match=r"\[tracker.floor\] n_templates: 0 is out of range; allowed: x >= 1"):
        FloorTrackerParams.from_dict({"n_templates": 0})
    with pytest.raises(ValueError, match=r"\[tracker.floor\] min_ncc: must be a number"):
        FloorTrackerParams.from_dict({"min_ncc": "high"})
    p = ORPRelocParams.from_dict({"scales": [[1, 1, 1]]})
    assert p.scales == ((1.0, 1.0, 1.0),)
    with pytest.raises(ValueError, match="must be a list of 3 numbers"):
        ORPRelocParams.from_dict({"scales": [[1.0, 1.0]]})


# --- the strict reader itself --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Knobs:
    a: float = knob(gt=0.0, lt=1.0)
    n: int = knob(ge=0, default=3)
    mode: str = knob(choices=("fast", "slow"), fold_case=True, default="fast")


def test_from_table_rules():
    assert from_table(_Knobs, {"a": 0.5}, name="t", partial=True) == _Knobs(0.5, 3, "fast")
    assert from_table(_Knobs, {"a": 0.5, "mode": "SLOW"}, name="t", partial=True).mode == "SLOW"
    with pytest.raises(ConfigError, match=r"^\[t\] n: missing \(an integer is required\)$"):
        from_table(_Knobs, {"a": 0.5}, name="t")
    with pytest.raises(ConfigError, match=r"^\[t\] a: 1 is out of range; allowed: 0 < x < 1$"):
        from_table(_Knobs, {"a": 1}, name="t", partial=True)
    with pytest.raises(ConfigError, match=r"^\[t\] a: must be a finite number, got inf$"):
        from_table(_Knobs, {"a": float("inf")}, name="t", partial=True)
    with pytest.raises(ConfigError, match=r"^\[t\] n: must be an integer, got a boolean true$"):
        from_table(_Knobs, {"a": 0.5, "n": True}, name="t", partial=True)
    with pytest.raises(ConfigError, match=r"^\[t\] x: unknown key \(known keys: a, n, mode\)$"):
        from_table(_Knobs, {"a": 0.5, "x": 1}, name="t", partial=True)


@pytest.mark.parametrize("example", sorted((REPO / "examples").glob("*.toml")), ids=lambda p: p.name)
def test_the_shipped_examples_pass(example):
    cfg = load_config(example)
    assert set(cfg) == set(default_config())
