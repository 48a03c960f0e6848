"""Replay a drive log against an exported bundle: what ``mosaicmap track`` runs
(:func:`track_log`; the command, :mod:`pipeline.cli.track`, is its options).

:func:`track_log` plays the vehicle: each frame of LOG is decoded and
rectified as ingest would (:class:`pipeline.camera.Rectifier`, at the bundle's pixel size),
then handed with the odometry's motion since the previous frame to a
:class:`tracker.session.Session` over the bundle (floor tracker, relative mode,
relocalization from the bundle's index). The frames are decoded before the timed loop
(:mod:`pipeline.track_replay`: in blocks, while the tracker is idle, as a camera delivers
them), so the figures time the tracker alone (what runs on the vehicle per frame: its fixes
and whole steps, wall and thread CPU clock); the command's own wall time is reported beside
them.

On an omni log (``[camera] model = "omni"``) the bundle's route panorama takes
the floor map's place: each frame's horizon line (:class:`tracker.orp.HorizonSampler` at
the route's samples per degree and horizon band, sampled from the raw frame divided pixel
by pixel by the log's flat field of :func:`pipeline.omni_ingest.omni_flat_field` per
``[ingest.flatfield] mode``: :class:`pipeline.omni_ingest.CorrectedHorizonLines`, the line
ingest writes to the horizons file) goes with the odometry's motion to a
:class:`tracker.orp_session.ORPSession` (localizer by view synthesis, gates, lost-lock
detection, global relocalization :mod:`tracker.orp_reloc`). BUNDLE may then also be a plain
zarr directory holding ``/routes/<id>`` (:mod:`mapstore.routes`). ``--route ID`` picks the
route (default: the only one, else the one nearest the start pose).

With ``ground_truth.csv`` in the log (simulated logs), errors are measured against it in
the map's frame: a simulated day's world frame is the map's frame when the map was built
from logs of the same world (their odometry starts on the ground truth; see the build's
``ground_truth.pose_rms_px``).
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.errors import BadInput
from pipeline.progress import counter, progress

_log = logging.getLogger(__name__)

__all__ = ["track_log", "summary_lines", "omni_summary_lines", "frame_loader"]

PREFETCH = 32


def _tracker_params(tcfg: dict, *tables: tuple[type, str]) -> tuple:
    """Each ``(settings class, key)``'s ``from_dict`` of ``[tracker.<key>]``, in order; a
    bad value is BadInput naming ``config[tracker]``."""
    try:
        return tuple(cls.from_dict(tcfg[key]) for cls, key in tables)
    except (ValueError, TypeError) as e:
        raise BadInput("config[tracker]", str(e)) from None


def _parse_start(text: str) -> str | np.ndarray:
    if text in ("odometry", "truth", "none"):
        return text
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        v = np.zeros(0)
    if len(v) != 3 or not np.isfinite(v).all():
        raise BadInput("--start", f"expected odometry, truth, none or X,Y,THETA (metres, radians), got {text!r}")
    return v


def _parse_frames(text: str | None, n: int) -> range:
    if text is None:
        return range(n)
    a, sep, b = text.partition(":")
    try:
        lo = int(a) if a else 0
        hi = int(b) if b else n
    except ValueError:
        raise BadInput("--frames", f"expected FIRST:LAST (frame rows, LAST excluded), got {text!r}") from None
    if not sep or not 0 <= lo < hi <= n:
        raise BadInput("--frames", f"expected FIRST:LAST with 0 <= FIRST < LAST <= {n}, got {text!r}")
    return range(lo, hi)


def frame_loader(lg, rect):
    """``load(i)``: frame row ``i`` of log ``lg`` decoded and rectified by ``rect`` (uint8),
    as ingest would; BadInput when its size differs from the log's first frame."""
    from pipeline.images import read_grey

    def load(i: int) -> np.ndarray:
        raw = read_grey(lg.image_path(i))
        if raw.shape != rect.raw_shape:
            raise BadInput(lg.image_path(i), f"image is {raw.shape[1]}x{raw.shape[0]}, the log's first frame is "
                                            f"{rect.raw_shape[1]}x{rect.raw_shape[0]}")
        h = None if lg.frame_heights is None else lg.frame_heights[i]
        return np.clip(np.rint(rect(raw, h)), 0, 255).astype(np.uint8)

    return load


def track_log(bundle: Path, log: Path, cfg: dict, *, start: str = "odometry", frames: str | None = None,
              route_id: str | None = None, keys: tuple[str, ...] = (), insecure: bool = False,
              plot: Path | None = None, poses: Path | None = None, quiet: bool = False,
              warn: Callable[[str], None] = _log.warning) -> tuple[dict, list[str]]:
    """Replay drive log ``log`` against map ``bundle`` with configuration ``cfg``: the
    report (a dict) and its printed summary lines. Options as ``mosaicmap track``'s
    (``frames`` = ``--frames FIRST:LAST``, ``keys`` = ``--key`` files); ``plot`` / ``poses``:
    files to write; ``warn(text)`` is told when a bundle is used unchecked (``insecure``).

    Per frame: a prior from the odometry, a pose fix against the map (status ok,
    low_texture, ambiguous, lost or off_map), frame-to-frame motion where the map has no
    data, relocalization when lost; an omni log on a route panorama. BadInput (one line)
    for a bad option, log or bundle.
    """
    from mapstore.bundle import BundleError
    from pipeline.camera import Rectifier
    from pipeline.drivelog import read_drive_log
    from pipeline.evaluate import ground_truth_at
    from pipeline.flatfield import calibration_flat_field
    from pipeline.images import read_grey
    from mapstore.grid import interpolate_trajectory, se2_between
    from tracker.bundle_map import open_bundle
    from tracker.floor import FloorTrackerParams
    from tracker.reloc import RelocParams, Relocalizer
    from pipeline.track_replay import frame_blocks, replay, speed_figures
    from tracker.session import Session, SessionParams, summarize

    t_cmd = time.perf_counter()
    start_spec = _parse_start(start)
    tcfg = cfg["tracker"]
    fparams, rparams, sparams = _tracker_params(tcfg, (FloorTrackerParams, "floor"), (RelocParams, "reloc"),
                                                (SessionParams, "session"))
    trust = _trust(tcfg["bundle"], keys, insecure, warn)
    lg = read_drive_log(log, follow_symlinks=bool(cfg["ingest"]["follow_symlinks"]))
    idx = _parse_frames(frames, len(lg.frame_images))
    t_frames = lg.frame_t[list(idx)]
    truth_csv = lg.path / "ground_truth.csv"
    truth = ground_truth_at(t_frames, truth_csv) if truth_csv.exists() else None
    if isinstance(start_spec, str) and start_spec == "truth" and truth is None:
        raise BadInput("--start", f"truth needs {truth_csv}, which does not exist")
    odo = interpolate_trajectory(lg.odometry, t_frames)
    # the start pose (world frame) or None: relocalize first
    if isinstance(start_spec, np.ndarray):
        start_pose = start_spec
    else:
        start_pose = {"odometry": odo[0], "truth": None if truth is None else truth[0], "none": None}[start_spec]
    if lg.camera.is_omni:
        rep = _track_omni(bundle, lg, idx, t_frames, odo, truth, start_pose, tcfg, start_spec, start, route_id,
                          plot, poses, quiet, t_cmd, cfg["ingest"]["flatfield"]["mode"], trust)
        return rep, omni_summary_lines(rep)
    if route_id is not None:
        raise BadInput("--route", f"is for omni logs on route panoramas; {log}'s camera is {lg.camera.model}")
    if bundle.is_dir():
        raise BadInput(bundle, f"a directory: a {lg.camera.model} log is tracked on a floor map, which needs a "
                               "bundle file (`mosaicmap export`)")
    try:
        tmap = open_bundle(bundle, keys=trust.keys, insecure=trust.insecure, limits=trust.limits)
    except BundleError as e:
        if bundle.is_file() and _routes_only(bundle):
            raise BadInput(bundle, f"holds route panoramas only (no floor map): a {lg.camera.model} log needs a "
                                   "floor map; route panoramas track omni logs") from None
        raise _refused(bundle, e) from None
    except (FileNotFoundError, IsADirectoryError):
        raise BadInput(bundle, "no such bundle file") from None
    except ValueError as e:
        raise BadInput(bundle, str(e)) from None
    trust.warn_unsigned(bundle, tmap.bundle.signed)
    with tmap, _reading(bundle):
        pixel_size = tmap.grid.pixel_size
        raw_shape = read_grey(lg.image_path(idx[0])).shape
        ing = cfg["ingest"]
        rect = Rectifier(lg.camera, raw_shape, pixel_size, interpolation=ing["interpolation"],
                         erode_px=ing["valid_mask_erode_px"], flat_field=calibration_flat_field(lg, raw_shape),
                         heights=lg.frame_heights)
        tracker = tmap.floor_tracker(pixel_size, fparams)
        t_idx = time.perf_counter()
        reloc = Relocalizer(tmap.feature_index(rparams), tracker, rparams)
        index_s = time.perf_counter() - t_idx
        session = Session(tracker, reloc, sparams)
        session.start(start_pose)
        motions = [None] + [se2_between(odo[k - 1], odo[k]) for k in range(1, len(idx))]
        # frames decoded before the timed loop, block by block (pipeline.track_replay)
        blocks = frame_blocks(frame_loader(lg, rect), idx, rect.valid.size)
        with counter(len(idx), label="track", unit="frames", quiet=quiet) as bar:
            run = replay(session, blocks, rect.valid, motions, on_step=bar.advance)
        steps = run.steps
        cache = {"tiles": tmap.tiles.capacity, "hits": tmap.tiles.hits, "misses": tmap.tiles.misses,
                 "reads_ahead": tmap.tiles.reads_ahead}
    rep = summarize(steps, truth, pixel_size)
    rep["speed"] = speed_figures(run, lambda sig: tracker.search_radius_px(sig, rect.valid.shape))
    rep.update({"bundle": str(bundle), "log": str(log), "log_id": lg.log_id, "frames_range": [idx.start, idx.stop],
                "pixel_size_m": pixel_size, "start": start if isinstance(start_spec, str) else start_spec.tolist(),
                "index_seconds": index_s, "index_source": tmap.index_source, "tile_cache": cache, "seconds": time.perf_counter() - t_cmd,
                "parameters": {"floor": tcfg["floor"], "reloc": tcfg["reloc"], "session": tcfg["session"]}})
    t_frames = lg.frame_t[list(idx)]
    if poses is not None:
        _write_poses(poses, t_frames, steps)
        rep["poses"] = str(poses)
    if plot is not None:
        from pipeline.plots import plot_tracking

        plot_tracking(plot, steps, odo, truth, pixel_size)
        rep["plot"] = str(plot)
    return rep, summary_lines(rep)


# --- omni logs on route panoramas -------------------------------------------------


@dataclass(frozen=True)
class Trust:
    """What ``track`` trusts: public keys (from --key and [tracker.bundle] trusted_keys),
    whether unsigned bundles are allowed (--insecure), the reading bounds."""

    keys: tuple
    insecure: bool
    limits: object
    warn: Callable[[str], None] = _log.warning

    def warn_unsigned(self, bundle: Path, signed: bool) -> None:
        if not signed:
            self.warn(f"--insecure: {bundle} is used without a signature check (development only)")


def _trust(table: dict, keys: tuple[str, ...], insecure: bool,
           warn: Callable[[str], None] = _log.warning) -> Trust:
    """The :class:`Trust` of ``track`` from ``[tracker.bundle]`` and the options."""
    from mapstore.bundle import BundleLimits
    from mapstore.signing import SignatureError, load_public_keys

    try:
        limits = BundleLimits.from_dict(table)
    except ValueError as e:
        raise BadInput("config[tracker.bundle]", str(e)) from None
    try:
        trusted = load_public_keys(table["trusted_keys"])
    except SignatureError as e:
        raise BadInput("config[tracker.bundle.trusted_keys]", str(e)) from None
    try:
        trusted += load_public_keys(keys)
    except SignatureError as e:
        raise BadInput("--key", str(e)) from None
    return Trust(trusted, insecure, limits, warn)


def _refused(bundle: Path, e) -> BadInput:
    """The one-line refusal of a bundle for BundleError ``e`` (its part and what)."""
    if e.part == "manifest.sig":
        return BadInput(bundle, f"refused: {e.part}: {e.what}")
    return BadInput(bundle, f"not a readable bundle: {e.part}: {e.what}")


class _reading:
    """A member found damaged or forged while tracking (first read of a tile or index
    chunk): one line naming the bundle and the member, exit 2."""

    def __init__(self, bundle: Path):
        self.bundle = bundle

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        from mapstore.bundle import BundleError

        if exc_type is not None and issubclass(exc_type, BundleError):
            raise BadInput(self.bundle, f"refused while reading: {exc.part}: {exc.what}") from None
        return False


def _open_routes(bundle: Path, trust: Trust | None = None):
    """``(zarr group, closer)`` over BUNDLE for its routes: a bundle file (read-only
    :class:`mapstore.bundle.BundleStore`, its signature checked against ``trust``) or a
    plain zarr directory (unsigned: --insecure only). BadInput when neither. ``trust``
    None: unchecked (only to name a bundle's routes in a message)."""
    import zarr

    from mapstore.bundle import SIGNATURE, BundleError, BundleStore, read_signature

    if bundle.is_dir() and trust is not None and not trust.insecure:
        raise BadInput(bundle, "refused: a zarr directory is unsigned; track a signed bundle (`mosaicmap export "
                               "--sign`), or use --insecure for development")
    if bundle.is_dir():
        try:
            return zarr.open_group(str(bundle), mode="r"), lambda: None
        except (zarr.errors.GroupNotFoundError, FileNotFoundError, ValueError, KeyError) as e:
            raise BadInput(bundle, f"not a zarr group holding routes ({e})") from None
    if not bundle.is_file():
        raise BadInput(bundle, "no such bundle file or map directory")
    try:
        store = BundleStore(bundle, **({} if trust is None else {"limits": trust.limits}))
    except BundleError as e:
        raise BadInput(bundle, f"not a readable bundle: {e.part}: {e.what}") from None
    except OSError as e:
        raise BadInput(bundle, f"cannot read ({e.strerror})") from None
    try:
        if trust is not None:
            if not trust.keys and not trust.insecure:
                raise BundleError(SIGNATURE, "no trusted key configured: a vehicle loads only signed bundles "
                                             "(track --key KEY.pub or [tracker.bundle] trusted_keys; --insecure for "
                                             "development)")
            try:
                if trust.keys:
                    store.index.trust = read_signature(store.index, trust.keys)
            except BundleError as e:
                if not (trust.insecure and e.what.startswith("missing")):
                    raise
            if store.index.trust is None:
                store.index.entries()  # unsigned: every member name checked at open
        return zarr.open_group(store=store, mode="r"), store.close
    except BundleError as e:
        store.close()
        raise _refused(bundle, e) from None
    except Exception as e:  # noqa: BLE001 (untrusted metadata: zarr raises many kinds)
        store.close()
        raise BadInput(bundle, f"not a readable bundle: zarr.json: {type(e).__name__}: {str(e)[:200]!r}") from None


def _routes_only(bundle: Path) -> bool:
    """Whether a bundle file holds route panoramas and no floor (unchecked: only to word a
    refusal; False when unreadable)."""
    from mapstore.routes import list_routes

    try:
        root, close = _open_routes(bundle)
    except BadInput:
        return False
    try:
        return "floor" not in root and bool(list_routes(root))
    except Exception:  # noqa: BLE001 - only a hint for an error message
        return False
    finally:
        close()


def _choose_route(bundle: Path, root, route_id: str | None, start_pose: np.ndarray | None):
    """``(route id, RouteRecord)``: ``route_id``, else the only route, else the route whose
    poses come nearest the start pose (world frame). BadInput naming what is missing."""
    from mapstore.routes import list_routes, read_route

    ids = list_routes(root)
    if not ids:
        raise BadInput(bundle, "holds no route panorama (/routes): an omni log is tracked on a route built "
                               "from omni logs")
    if route_id is not None:
        if route_id not in ids:
            raise BadInput("--route", f"no route {route_id!r} in {bundle} (routes: {', '.join(ids)})")
        ids = [route_id]
    if len(ids) > 1 and start_pose is None:
        raise BadInput("--route", f"{bundle} holds {len(ids)} routes ({', '.join(ids)}): name one with --route "
                                  "when the start pose is unknown (--start none)")
    best = None
    for rid in ids:
        try:
            rec = read_route(root, rid)
        except (ValueError, KeyError, RuntimeError, TypeError) as e:  # damaged chunks of an unsigned bundle
            raise BadInput(bundle, f"route {rid}: {e}") from None
        d = 0.0 if start_pose is None else float(np.min(np.hypot(*(rec.poses[:, :2] - start_pose[:2]).T)))
        if best is None or d < best[0]:
            best = (d, rid, rec)
    return best[1], best[2]


def _track_omni(bundle: Path, lg, idx: range, t_frames: np.ndarray, odo: np.ndarray, truth: np.ndarray | None,
                start_pose: np.ndarray | None, tcfg: dict, start_spec, start: str, route_id: str | None,
                plot: Path | None, poses: Path | None, quiet: bool, t_cmd: float,
                flat_mode: str, trust: Trust) -> dict:
    """``mosaicmap track`` on an omni log: the route panorama session (see the module docstring).
    ``t_frames``, ``odo``, ``truth``: times, odometry and ground truth (or None) of the frames;
    ``flat_mode`` is ``[ingest.flatfield] mode``: the flat field ingest applied to the route's lines.
    Returns the report."""
    from mapstore.grid import se2_between
    from pipeline.images import read_grey
    from pipeline.omni_ingest import CorrectedHorizonLines, omni_flat_field
    from tracker.orp import ORP, ORPLocalizer, ORPParams
    from tracker.orp_reloc import ORPRelocalizer, ORPRelocParams
    from tracker.orp_session import ORPSession, ORPSessionParams, summarize

    oparams, sparams, rparams = _tracker_params(tcfg, (ORPParams, "orp"), (ORPSessionParams, "orp_session"),
                                                (ORPRelocParams, "orp_reloc"))
    root, close = _open_routes(bundle, trust)
    try:
        with _reading(bundle):
            rid, record = _choose_route(bundle, root, route_id, start_pose)
        index = getattr(root.store, "index", None)
        trust.warn_unsigned(bundle, index is not None and index.trust is not None)
    finally:
        close()
    try:
        orp = ORP.from_record(record)
    except ValueError as e:
        raise BadInput(bundle, f"route {rid}: {e}") from None
    t_idx = time.perf_counter()
    loc = ORPLocalizer(orp, oparams)
    reloc = ORPRelocalizer(loc, rparams)
    index_s = time.perf_counter() - t_idx
    session = ORPSession(loc, reloc, sparams)
    session.start(start_pose)
    sampler = ORPSession.sampler_for(orp, lg.camera.omni, oparams)
    raw_shape = read_grey(lg.image_path(idx[0])).shape
    flat, flat_info = omni_flat_field(lg, raw_shape, flat_mode)
    horizon_line = CorrectedHorizonLines(sampler, raw_shape, flat)

    def load(i: int) -> np.ndarray:
        raw = read_grey(lg.image_path(i))
        if raw.shape != raw_shape:
            raise BadInput(lg.image_path(i), f"image is {raw.shape[1]}x{raw.shape[0]}, the log's first frame is "
                                            f"{raw_shape[1]}x{raw_shape[0]}")
        return raw

    steps, unwarp = [], []
    rows = list(idx)
    with ThreadPoolExecutor(2) as pool:
        frames = (im for k in range(0, len(rows), PREFETCH) for im in pool.map(load, rows[k : k + PREFETCH]))
        for k, raw in enumerate(progress(frames, length=len(rows), label="track", unit="frames", quiet=quiet)):
            t0 = time.perf_counter()
            line = horizon_line(raw)
            unwarp.append(time.perf_counter() - t0)
            motion = None if k == 0 else se2_between(odo[k - 1], odo[k])
            steps.append(session.step(line, motion))
    rep = summarize(steps, truth)
    unwarp_ms = 1000.0 * float(np.mean(unwarp))
    rep.update({"bundle": str(bundle), "log": str(lg.path), "log_id": lg.log_id, "camera": "omni",
                "frames_range": [idx.start, idx.stop], "route": rid, "route_rows": int(len(orp.lines)),
                "route_length_m": orp.length_m, "route_spacing_m": orp.spacing_m,
                "route_samples_per_degree": orp.samples_per_degree,
                "start": start if isinstance(start_spec, str) else start_spec.tolist(),
                "index_seconds": index_s, "index_source": "route", "flat_field": flat_info, "unwarp_ms": unwarp_ms,
                "ms_per_frame": unwarp_ms + 1000.0 * rep["tracker_seconds"] / max(len(steps), 1),
                "seconds": time.perf_counter() - t_cmd,
                "parameters": {"orp": tcfg["orp"], "orp_session": tcfg["orp_session"], "orp_reloc": tcfg["orp_reloc"]}})
    if poses is not None:
        _write_poses(poses, t_frames, steps)
        rep["poses"] = str(poses)
    if plot is not None:
        from pipeline.plots import ORP_STATUS_COLOURS, plot_tracking

        plot_tracking(plot, steps, odo, truth, 0.01, "cm", 100.0 * float(rep.get("wrong_m", 0.10)), ORP_STATUS_COLOURS,
                      orp.poses)
        rep["plot"] = str(plot)
    return rep


def omni_summary_lines(rep: dict) -> list[str]:
    """The printed summary of a track report on a route panorama."""
    st = ", ".join(f"{k} {v}" for k, v in sorted(rep["statuses"].items()))
    md = ", ".join(f"{k} {v}" for k, v in rep["modes"].items() if v)
    out = [f"track {rep['log_id']} on {rep['bundle']} route {rep['route']} ({rep['route_length_m']:.2f} m): "
           f"{rep['fixes']} frames, ok {rep['ok']} ({100 * rep['ok_rate']:.2f} %); statuses: {st}; poses from: {md}"]
    if rep["fixes_per_s"] is not None:
        lat, cpu = rep["latency_ms"], rep["cpu_latency_ms"]
        out.append(f"speed: {rep['fixes_per_s']:.0f} fixes/s, latency p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, "
                   f"max {lat['max']:.2f} ms (CPU p50 {cpu['p50']:.2f} ms); horizon unwarp {rep['unwarp_ms']:.2f} ms; "
                   f"{rep['ms_per_frame']:.2f} ms per frame in all")
    rl = rep["relocalization"]
    if rl["attempts"]:
        out.append(f"relocalization: {rep['relocalizations']} successful of {rl['attempts']} attempts, "
                   f"median {1000 * rl['seconds_median']:.0f} ms, max {1000 * rl['seconds_max']:.0f} ms")
    if rep.get("error_rms_m") is not None:
        out.append(f"vs ground truth (ok frames): mean {100 * rep['error_mean_m']:.2f} cm, RMS {100 * rep['error_rms_m']:.2f} cm, "
                   f"max {100 * rep['error_max_m']:.2f} cm, heading RMS {rep['heading_rms_deg']:.3f} deg; "
                   f"wrong ok (> {100 * rep['wrong_m']:g} cm): {rep['wrong_ok']}")
    out.append(f"seconds: {rep['seconds']:.1f} (tracker {rep['tracker_seconds']:.1f})")
    return out


def _write_poses(path: Path, t: np.ndarray, steps) -> None:
    from pipeline.fsutil import write_text_atomic

    lines = ["t,x,y,theta,status,mode,sigma_x,sigma_y,sigma_theta"]
    for ti, st in zip(t, steps):
        p, s = [repr(float(v)) for v in st.pose], [repr(float(v)) for v in st.sigma]
        lines.append(f"{float(ti)!r},{p[0]},{p[1]},{p[2]},{st.status},{st.mode},{s[0]},{s[1]},{s[2]}")
    write_text_atomic(path, "\n".join(lines) + "\n")


def summary_lines(rep: dict) -> list[str]:
    """The printed summary of a track report."""
    from pipeline.track_replay import speed_line

    st = ", ".join(f"{k} {v}" for k, v in sorted(rep["statuses"].items()))
    md = ", ".join(f"{k} {v}" for k, v in rep["modes"].items() if v)
    lat = rep["latency_ms"]
    out = [f"track {rep['log_id']} on {rep['bundle']}: {rep['fixes']} frames, ok {rep['ok']} "
           f"({100 * rep['ok_rate']:.2f} %); statuses: {st}; poses from: {md}"]
    if rep.get("speed") is not None:
        out.append(speed_line(rep["speed"]))
    elif rep["fixes_per_s"] is not None:
        cpu = rep["cpu_latency_ms"]
        out.append(f"speed: {rep['fixes_per_s']:.0f} fixes/s, latency p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms, "
                   f"max {lat['max']:.2f} ms (tracker only, one thread; in CPU time {rep['cpu_fixes_per_s']:.0f} "
                   f"fixes/s, p50 {cpu['p50']:.2f} ms, p99 {cpu['p99']:.2f} ms)")
    rl = rep["relocalization"]
    if rl["attempts"]:
        out.append(f"relocalization: {rep['relocalizations']} successful of {rl['attempts']} attempts, "
                   f"median {rl['seconds_median']:.2f} s, max {rl['seconds_max']:.2f} s ({rep['index_source']} index "
                   f"ready in {rep['index_seconds']:.2f} s)")
    if rep.get("error_rms_px") is not None:
        out.append(f"vs ground truth (ok fixes): RMS {rep['error_rms_px']:.3f} px, median {rep['error_median_px']:.3f} px, "
                   f"max {rep['error_max_ok_px']:.3f} px, heading RMS {rep['heading_error_rms_deg']:.3f} deg; "
                   f"wrong ok (> {rep['wrong_px']:g} px): {rep['wrong_ok']}")
    rel = rep.get("relative")
    if rel and rel["frames"]:
        g = rel["error_growth_per_m"]
        out.append(f"relative mode: {rel['frames']} frames over {rel['length_m']:.2f} m in {len(rel['stretches'])} "
                   f"stretch(es); error growth {'n/a' if g is None else f'{100 * g:.2f} % of distance'}")
    out.append(f"seconds: {rep['seconds']:.1f} (tracker {rep['tracker_seconds']:.1f})")
    return out
