"""The route panorama session (tracker.orp_session), global relocalization (tracker.orp_reloc),
ORP.from_record and `mosaicmap track` on omni logs (issue 7).

Session and relocalization tests use the analytic room of tests/test_orp.py (horizon lines by
ray casting to textured walls); the CLI tests simulate a tiny omni world (240 x 240 frames,
a 7 m loop every 4 cm) and store its route in a plain zarr directory and in a zip of it.
"""

from __future__ import annotations

import json
import math
import zipfile

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapstore.grid import se2_between, se2_compose
from mapstore.routes import RouteRecord, write_route
from test_orp import horizon_line
from tracker.orp import ORP, HorizonSampler, ORPLocalizer, ORPParams, build_orp
from tracker.orp_reloc import ORPRelocalizer, ORPRelocParams
from tracker.orp_session import ORPSession, ORPSessionParams, summarize


def s_route(n: int = 301, step: float = 0.02) -> np.ndarray:
    """Poses of a gently S-shaped route through the 8 x 5 m room (world frame), ``step`` apart."""
    out = [np.array([1.0, 2.2, 0.0])]
    for k in range(n - 1):
        out.append(se2_compose(out[-1], np.array([step, 0.0, 0.012 * math.sin(k / 60.0)])))
    return np.array(out)


@pytest.fixture(scope="module")
def route():
    poses = s_route()
    orp = build_orp(np.stack([horizon_line(p) for p in poses]), poses, 0.02, 1.0)
    loc = ORPLocalizer(orp, ORPParams())
    return orp, loc, ORPRelocalizer(loc)


def drive(poses: np.ndarray, offset=(0.0, 0.03, 0.02)) -> np.ndarray:
    """A held-out drive: the route's poses moved by ``offset`` (vehicle frame)."""
    return np.array([se2_compose(p, np.asarray(offset, float)) for p in poses])


def odometry_motions(truth: np.ndarray, rng, drift: float = 0.02) -> list[np.ndarray]:
    """Odometry motions between frames with errors of ``drift`` x distance (vehicle frame)."""
    out = []
    for k in range(1, len(truth)):
        m = se2_between(truth[k - 1], truth[k])
        out.append(m + rng.normal(0, drift * np.hypot(m[0], m[1]), 3) * [1, 1, 0.5])
    return out


def run(session: ORPSession, lines, motions):
    steps = [session.step(lines[0], None)]
    for k in range(1, len(lines)):
        steps.append(session.step(lines[k], motions[k - 1]))
    return steps


def test_from_record_round_trips_the_stored_route(route, tmp_path):
    import zarr

    from mapstore.routes import read_route

    orp = route[0]
    root = zarr.open_group(str(tmp_path / "m.zarr"), mode="w")
    write_route(root, "s", RouteRecord(orp.lines, orp.poses, 0.5, 0.02, 1.0, 1.5, version=3, meta={"runs": 2}))
    back = ORP.from_record(read_route(zarr.open_group(str(tmp_path / "m.zarr"), mode="r"), "s"))
    np.testing.assert_array_equal(back.lines, orp.lines)
    np.testing.assert_allclose(back.poses, orp.poses)
    assert (back.s0, back.spacing_m, back.samples_per_degree, back.horizon_band_deg) == (0.5, 0.02, 1.0, 1.5)
    assert back.meta["runs"] == 2 and back.meta["version"] == 3
    with pytest.raises(ValueError, match="at least 2 rows"):
        ORP.from_record(RouteRecord(orp.lines[:1], orp.poses[:1]))


def test_session_tracks_with_odometry_priors(route):
    orp, loc, reloc = route
    truth = drive(orp.poses[10:260:2].astype(float))
    lines = [horizon_line(p) for p in truth]
    sess = ORPSession(loc, reloc)
    sess.start(se2_compose(truth[0], np.array([0.03, -0.02, 0.02])))
    steps = run(sess, lines, odometry_motions(truth, np.random.default_rng(1)))
    rep = summarize(steps, truth)
    assert rep["ok_rate"] == 1.0 and rep["modes"]["fix"] == len(truth), rep["statuses"]
    assert rep["error_mean_m"] < 0.002 and rep["error_max_m"] < 0.01 and rep["heading_rms_deg"] < 0.1
    assert rep["wrong_ok"] == 0 and rep["fixes_per_s"] > 0 and rep["latency_ms"]["p50"] > 0
    assert all(st.sigma[0] == pytest.approx(ORPSessionParams().fix_sigma_m) for st in steps)


def test_statuses_weak_lost_off_route_and_sigma_growth(route):
    orp, loc, _ = route
    rng = np.random.default_rng(2)
    p = ORPSessionParams()
    # no relocalizer: garbage lines are weak, then the session is lost and stays lost
    sess = ORPSession(loc, None, p)
    truth = drive(orp.poses[50:70].astype(float))
    sess.start(truth[0])
    noise = [rng.uniform(0, 255, 360).astype(np.float32) for _ in truth]
    steps = run(sess, noise, odometry_motions(truth, rng, 0.0))
    assert [st.status for st in steps[: p.lost_after]] == ["weak"] * p.lost_after
    assert all(st.status == "lost" and st.mode == "odometry" for st in steps[p.lost_after:])
    assert not any(st.ok for st in steps)
    # the 1-sigma grows with the distance driven (error gradient x metres)
    d = float(np.sum(np.hypot(*np.diff(truth[:, :2], axis=0).T)))
    assert steps[-1].sigma[0] == pytest.approx(p.start_sigma_m + p.error_gradient * d, rel=1e-6)
    # a prediction 2 m beside the route: off_route, dead reckoning, not a failure
    sess.start(se2_compose(truth[0], np.array([0.0, 2.0, 0.0])))
    st = sess.step(horizon_line(truth[0]), None)
    assert st.status == "off_route" and st.mode == "odometry" and st.fix is None and not st.lost
    # no pose at all and no relocalizer: lost, mode none
    sess.start(None)
    st = sess.step(horizon_line(truth[0]), None)
    assert st.status == "lost" and st.mode == "none" and np.isnan(st.pose).all()


def test_wrong_prior_is_never_a_confident_wrong_ok_then_relocalizes(route):
    orp, loc, reloc = route
    truth = drive(orp.poses[100:200:2].astype(float), (0.0, -0.05, -0.03))
    lines = [horizon_line(p) for p in truth]
    motions = odometry_motions(truth, np.random.default_rng(3))
    wrong = se2_compose(truth[0], np.array([0.9, 0.15, 0.1]))  # 90 cm along, 15 cm across
    # without relocalization: never ok far from the truth; lost after lost_after failures
    sess = ORPSession(loc, None)
    sess.start(wrong)
    steps = run(sess, lines, motions)
    err = np.array([np.hypot(*(st.pose[:2] - t[:2])) for st, t in zip(steps, truth)])
    assert not any(st.ok and e > 0.10 for st, e in zip(steps, err))
    assert steps[-1].lost and steps[-1].status == "lost"
    assert {st.status for st in steps[:5]} <= {"weak", "jump", "masked"}
    # with it: lost, then relocalized, then tracked within millimetres
    sess = ORPSession(loc, reloc)
    sess.start(wrong)
    steps = run(sess, lines, motions)
    rep = summarize(steps, truth)
    assert rep["wrong_ok"] == 0 and rep["relocalizations"] >= 1 and rep["relocalization"]["first_ok_frame"] <= 8
    assert all(st.ok for st in steps[rep["relocalization"]["first_ok_frame"]:])
    assert rep["error_max_m"] < 0.01


def test_kidnapped_start_relocalizes_everywhere_on_the_route(route):
    orp, loc, reloc = route
    truth = drive(orp.poses[5:300:25].astype(float), (0.0, 0.08, 2.5))  # turned 143 deg, 8 cm beside
    for t in truth:
        res = reloc.locate(horizon_line(t))
        assert res.ok, (t, res.status)
        assert np.hypot(*(res.fix.pose[:2] - t[:2])) < 0.01
        assert abs(math.remainder(res.fix.pose[2] - t[2], 2 * math.pi)) < math.radians(0.5)
    sess = ORPSession(loc, reloc)
    sess.start(None)
    st = sess.step(horizon_line(truth[3]), None)
    assert st.status == "ok" and st.mode == "reloc" and st.reloc_seconds > 0


def test_a_repeated_place_is_ambiguous_not_a_wrong_fix(route):
    orp = route[0]
    # the same 3 m of route twice, the second copy 10 m away: every line fits both places
    half = slice(0, 151)
    poses = np.concatenate([orp.poses[half], orp.poses[half] + np.array([0.0, 10.0, 0.0], np.float32)])
    twin = ORP(np.concatenate([orp.lines[half], orp.lines[half]]), poses, 0.0, 0.02, 1.0)
    reloc = ORPRelocalizer(ORPLocalizer(twin), ORPRelocParams())
    res = reloc.locate(horizon_line(drive(orp.poses[70:71].astype(float))[0]))
    assert res.status == "ambiguous" and not res.ok and res.runner_up is not None
    assert abs(np.hypot(*(res.fix.pose[:2] - res.runner_up.pose[:2])) - 10.0) < 0.05
    sess = ORPSession(ORPLocalizer(twin), reloc)
    sess.start(None)
    st = sess.step(horizon_line(orp.poses[70]), None)
    assert st.status == "ambiguous" and st.mode == "none"


def test_configs_tracker_toml_equals_the_defaults():
    from pipeline.config import load_config

    cfg = load_config(None)["tracker"]
    assert ORPSessionParams.from_dict(cfg["orp_session"]) == ORPSessionParams()
    assert ORPRelocParams.from_dict(cfg["orp_reloc"]) == ORPRelocParams()
    with pytest.raises(ValueError, match=r"\[tracker.orp_session\] lost_afterr: unknown key"):
        ORPSessionParams.from_dict({"lost_afterr": 3})
    with pytest.raises(ValueError, match=r"\[tracker.orp_reloc\] candidate: unknown key"):
        ORPRelocParams.from_dict({"candidate": 3})


def test_orp_modules_import_nothing_from_pipeline():
    from conftest import modules_pulled_in

    assert modules_pulled_in(["tracker.orp_session", "tracker.orp_reloc"], ("pipeline",)) == []


# --- `mosaicmap track` on omni logs ------------------------------------------------------

TINY = """
[simulate.omni]
room_m = [5.0, 4.0]
[simulate.omni.camera]
frame_size = [240, 240]
[simulate.omni.motion]
frame_spacing_m = 0.04
[simulate.omni.routes]
inset_m = 1.2
loop_corner_radius_m = 0.6
[simulate.omni.world]
objects = 3
object_size_m = [0.2, 0.5]
object_height_m = [1.2, 2.0]
texel_m = 0.02
"""


def invoke(*args):
    from pipeline.cli import cli

    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def omni_site(tmp_path_factory):
    """A memorized tiny omni run's route (ground-truth poses) in a zarr directory and a zip of
    it, a held-out run 5 cm beside it, an empty zarr group."""
    import zarr

    from mapstore.grid import interpolate_trajectory
    from pipeline.drivelog import read_drive_log, read_pose_csv

    root = tmp_path_factory.mktemp("omni")
    cfg = root / "tiny.toml"
    cfg.write_text(TINY)
    for name, extra in (("mem", []), ("run", ["--world", root / "mem", "--seed", "3", "--offset", "0.05"])):
        r = invoke("simulate", "omni", root / name, "--config", cfg, "--quiet", *extra)
        assert r.exit_code == 0, r.output
    log = read_drive_log(root / "mem")
    hs = HorizonSampler(log.camera.omni, 1.0, 1.0, 3)
    truth = interpolate_trajectory(read_pose_csv(root / "mem" / "ground_truth.csv"), log.frame_t)
    gain = log.camera.omni.vignetting_gain((240, 240), log.camera.vignetting)  # declared: lines as ingest's
    lines = hs.lines(cv2.imread(str(log.image_path(i)), cv2.IMREAD_GRAYSCALE) / gain
                     for i in range(len(log.frame_images)))
    orp = build_orp(lines, truth, 0.02, 1.0)
    g = zarr.open_group(str(root / "map.zarr"), mode="w")
    write_route(g, "loop", RouteRecord(orp.lines, orp.poses, 0.0, orp.spacing_m, 1.0, 1.0))
    with zipfile.ZipFile(root / "map.zip", "w", zipfile.ZIP_STORED) as z:
        for p in sorted((root / "map.zarr").rglob("*")):
            if p.is_file():
                z.write(p, p.relative_to(root / "map.zarr").as_posix())
    zarr.open_group(str(root / "empty.zarr"), mode="w")
    return root


def test_cli_track_an_omni_log_on_a_route(omni_site, tmp_path):
    rep_path, plot, poses = tmp_path / "t.json", tmp_path / "t.png", tmp_path / "p.csv"
    r = invoke("track", omni_site / "map.zarr", omni_site / "run", "--report", rep_path, "--plot", plot,
               "--poses", poses, "--quiet", "--insecure")
    assert r.exit_code == 0, r.output
    rep = json.loads(rep_path.read_text())
    for key in ("fixes", "ok_rate", "statuses", "modes", "fixes_per_s", "latency_ms", "relocalizations",
                "error_rms_m", "error_mean_m", "error_max_m", "heading_rms_deg", "wrong_ok", "ms_per_frame"):
        assert key in rep, key
    assert rep["route"] == "loop" and rep["camera"] == "omni"
    assert rep["ok_rate"] > 0.9 and rep["wrong_ok"] == 0 and rep["error_mean_m"] < 0.02, rep
    assert cv2.imread(str(plot)).shape[2] == 3
    rows = poses.read_text().splitlines()
    assert rows[0].startswith("t,x,y,theta,status,mode") and len(rows) == rep["fixes"] + 1
    assert "wrong ok (> 10 cm): 0" in r.output and "fixes/s" in r.output
    # kidnapped, from the zip: relocalized without a prior, never a wrong ok
    r = invoke("track", omni_site / "map.zip", omni_site / "run", "--start", "none", "--frames", "0:15",
               "--route", "loop", "--report", rep_path, "--quiet", "--insecure")
    assert r.exit_code == 0, r.output
    rep = json.loads(rep_path.read_text())
    assert rep["fixes"] == 15 and rep["relocalizations"] >= 1 and rep["wrong_ok"] == 0 and rep["ok_rate"] > 0.8


def _tracked_lines(monkeypatch, *args) -> np.ndarray:
    """The horizon lines `mosaicmap track` hands to the session, one per frame ``(N, A)``."""
    seen: list[np.ndarray] = []
    step = ORPSession.step

    def spy(self, line, motion=None):
        seen.append(np.array(line, copy=True))
        return step(self, line, motion)

    monkeypatch.setattr(ORPSession, "step", spy)
    r = invoke("track", *args, "--quiet", "--insecure")
    monkeypatch.setattr(ORPSession, "step", step)
    assert r.exit_code == 0, r.output
    return np.stack(seen)


def test_cli_track_omni_lines_equal_the_ingest_horizons_file(omni_site, tmp_path, monkeypatch):
    """A log with declared vignetting: the line the vehicle computes for each frame is the line
    ingest wrote to the horizons file for that frame (same flat field, corrected pixel by
    pixel before sampling); ``[ingest.flatfield] mode = "none"`` is honoured by both."""
    from pipeline.drivelog import read_drive_log
    from pipeline.omni_ingest import read_horizons

    lg = read_drive_log(omni_site / "run")
    assert lg.camera.vignetting is not None
    r = invoke("build", omni_site / "run", "-w", tmp_path / "w", "--until", "ingest", "--config",
               omni_site / "tiny.toml", "-q")
    assert r.exit_code == 0, r.output
    h = read_horizons(tmp_path / "w" / "ingest" / "horizons" / "000.npz")
    np.testing.assert_array_equal(h["frame"], np.arange(len(lg.frame_images)))
    live = _tracked_lines(monkeypatch, omni_site / "map.zarr", omni_site / "run", "--frames", "0:40")
    assert live.shape == (40, 360) and live.dtype == np.float32
    np.testing.assert_allclose(live, h["lines"][:40], rtol=1e-6, atol=1e-5)
    # mode "none": no correction at all (the raw frame's line), not the calibration's
    cfg = tmp_path / "none.toml"
    cfg.write_text(TINY + '[ingest.flatfield]\nmode = "none"\n')
    live_none = _tracked_lines(monkeypatch, omni_site / "map.zarr", omni_site / "run", "--frames", "0:5",
                               "--config", cfg)
    hs = HorizonSampler(lg.camera.omni, 1.0, 1.0, 3)
    raw = np.stack([hs.line(cv2.imread(str(lg.image_path(i)), cv2.IMREAD_GRAYSCALE).astype(np.float32))
                    for i in range(5)])
    np.testing.assert_allclose(live_none, raw, rtol=1e-6, atol=1e-5)
    assert np.abs(live_none - h["lines"][:5]).max() > 1.0


def test_cli_track_omni_bad_input(omni_site, tmp_path):
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"not a bundle")
    cases = [(("track", omni_site / "empty.zarr", omni_site / "run"), "no route panorama"),
             (("track", omni_site / "map.zarr", omni_site / "run", "--route", "nope"), "--route"),
             (("track", junk, omni_site / "run"), "junk.zip"),
             (("track", tmp_path / "none.zip", omni_site / "run"), "none.zip"),
             (("track", omni_site / "map.zip", omni_site / "run", "--start", "1,2"), "--start")]
    for args, what in cases:
        r = invoke(*args, "--insecure")
        assert r.exit_code == 2, (args, r.output)
        assert what in r.output and len(r.output.strip().splitlines()) == 1, r.output


def test_cli_track_a_downward_log_on_routes_only(omni_site, small_log):
    for bundle, what in ((omni_site / "map.zarr", "directory"), (omni_site / "map.zip", "route panoramas only")):
        r = invoke("track", bundle, small_log)
        assert r.exit_code == 2 and what in r.output and len(r.output.strip().splitlines()) == 1, r.output
    r = invoke("track", omni_site / "map.zip", small_log, "--route", "loop")
    assert r.exit_code == 2 and "--route" in r.output, r.output


def test_cli_track_omni_needs_a_signed_route_bundle(omni_site, tmp_path):
    """A route bundle signed by the map owner tracks with --key; the same routes unsigned,
    or forged (a line chunk changed, hashes and seal recomputed), are refused in one line."""
    from bundle_forge import forge
    from mapstore.bundle import BundleWriter, member_key
    from mapstore.signing import signature_document, load_private_key

    assert invoke("keys", "new", tmp_path / "k").exit_code == 0
    key = load_private_key(tmp_path / "k")
    src = omni_site / "map.zarr"
    files = sorted((p.relative_to(src).as_posix(), p) for p in src.rglob("*") if p.is_file())
    signed = tmp_path / "routes.zip"
    header = {"format": "mosaicmap-bundle", "format_version": 1, "kind": "full", "map_id": "test",
              "version": {"snapshot": "s", "tags": [], "number": 1}, "created": "2026-01-01T00:00:00+00:00",
              "selection": {"kind": "all"}, "bounds_m": [0, 0, 0, 0], "grid": None, "tile_px": None, "levels": {},
              "layers": {}, "routes_only": True, "routes": []}
    with BundleWriter(signed, sign=lambda m: signature_document(m, key)) as w:
        for name, p in sorted(files, key=lambda f: member_key(f[0])):
            w.add(name, p.read_bytes())
        w.finish(header)
    pub = tmp_path / "k.pub"
    r = invoke("track", signed, omni_site / "run", "--key", pub, "--frames", "0:5", "--quiet")
    assert r.exit_code == 0 and "warning" not in r.output, r.output
    forged = tmp_path / "forged.zip"
    forge(signed, forged, lambda m: {k: (v[::-1] if "/lines/c/" in k else v) for k, v in m.items()})
    for bundle, what in ((forged, "forged or damaged"), (omni_site / "map.zip", "not signed"),
                         (omni_site / "map.zarr", "unsigned")):
        r = invoke("track", bundle, omni_site / "run", "--key", pub, "--frames", "0:5", "--quiet")
        assert r.exit_code == 2 and what in r.output and len(r.output.strip().splitlines()) == 1, r.output
