"""Stage ``publish``: quality gates, then one atomic icechunk commit and a tag.

The render stage's shards (``WORKDIR/render/map.zarr``, listed in ``touched.json``) are
copied into a writable session on the branch, whole shards only, with the map's pose table
extended by this build's frames; one ``commit`` makes them visible at once (a killed
publish leaves the branch as it was). Commits are serialized by the repository's commit
lock, and a build publishes only onto the map version it was built against: when the
branch moved meanwhile, publish refuses (exit 1) rather than overwrite another build.

Route panoramas (the ``orp`` stage's ``WORKDIR/orp/<route_id>.npz``) go into the same commit
(:func:`mapstore.routes.write_route`, with the publish version and their source logs) when the
``orp`` stage is part of this build (run or found up to date: it is in the report's
``stages``); route files an earlier build left in a reused workdir are not published. A build
of omni logs without floor frames publishes its routes alone.

Geographic reference: when every log of the build that creates a map is geotagged with one
origin (``mosaicmap import-geotagged`` writes ``[source] origin_latitude/origin_longitude``
to drive.toml, and the logs share the site's odometry frame, i.e. that local east/north
plane), the map records it as its ``geo_reference`` root attribute (:mod:`mapstore.layout`),
so a diff can give its regions in WGS 84. Logs of another origin, or a map without one, are
warned about and change nothing.

A build that fails a quality gate ([publish] in configs/floor.toml) does not publish; the
gates are also checked before rendering, so a failing build stops early.
"""

from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import zarr

from mapstore.layout import (
    LAYERS_GROUP,
    PoseTable,
    create_floor,
    read_floor,
    read_poses,
    resize_floor,
    set_version,
    write_poses,
)
from mapstore.grid import GeoReference, MapGrid
from pipeline import __version__
from pipeline.errors import BadInput, JobFailed
from pipeline.geometry_gate import dropped_mask, extent_growth_m, extent_tolerance_m
from pipeline.mosaic import shard_box
from pipeline.stages.stage import Stage, StageParams
from pipeline.stages.workspace import Workspace

log = logging.getLogger(__name__)


def check_gates(report: dict, cfg_pub: dict) -> None:
    """Raise :class:`JobFailed` naming the first quality gate the build's figures fail."""
    links = report.get("links", {})
    opt = report.get("optimization", {})
    cand = links.get("candidates", 0)
    if cand:
        frac = links.get("accepted", 0) / cand
        if frac < cfg_pub["min_accepted_fraction"]:
            raise JobFailed(f"quality gate: {frac:.1%} of candidate links accepted "
                            f"(min {cfg_pub['min_accepted_fraction']:.0%} [publish] min_accepted_fraction); not published")
    tried = links.get("frames_tried", 0)
    if tried and "max_unlinked_fraction" in cfg_pub:
        frac = links.get("frames_unlinked", 0) / tried
        if frac > cfg_pub["max_unlinked_fraction"]:
            names = ", ".join(links.get("unlinked", [])[:5])
            raise JobFailed(f"quality gate: {frac:.1%} of the textured frames with candidate pairs keep no accepted "
                            f"link and rest on their prior alone (max {cfg_pub['max_unlinked_fraction']:.0%} "
                            f"[publish] max_unlinked_fraction; e.g. {names}); not published")
    reg = links.get("frames_registrable", 0)
    if reg and "max_unverified_overlap_fraction" in cfg_pub:
        frac = links.get("unverified_overlap_frames", 0) / reg
        if frac > cfg_pub["max_unverified_overlap_fraction"]:
            names = ", ".join(links.get("unverified_overlap", [])[:5])
            raise JobFailed(f"quality gate: {frac:.1%} of the textured frames overlap a frame no chain of links ties "
                            f"them to, placed against it by the prior alone: the mosaic may be doubled there (max "
                            f"{cfg_pub['max_unverified_overlap_fraction']:.0%} [publish] "
                            f"max_unverified_overlap_fraction; e.g. {names}); not published")
    rms = opt.get("residual_rms_px", 0.0)
    if rms > cfg_pub["max_residual_rms_px"]:
        raise JobFailed(f"quality gate: link residual RMS {rms:.3f} px after optimization "
                        f"(max {cfg_pub['max_residual_rms_px']} px [publish] max_residual_rms_px); not published")
    worst = opt.get("residual_max_px", 0.0)
    if worst > cfg_pub["max_residual_px"]:
        raise JobFailed(f"quality gate: an accepted link keeps a residual of {worst:.3f} px "
                        f"(max {cfg_pub['max_residual_px']} px [publish] max_residual_px); not published")
    geo = report.get("geometry", {})
    linked = geo.get("linked_extent_m")
    extent = report.get("render", {}).get("extent_m") or geo.get("extent_m")
    if linked and extent and "max_extent_growth_fraction" in cfg_pub:
        growth = extent_growth_m(extent, linked)
        tol = extent_tolerance_m(linked, float(geo.get("frame_diagonal_m", 0.0)), cfg_pub)
        if growth > tol:
            raise JobFailed(f"quality gate: frames without an accepted link reach {growth:.4g} m beyond the linked "
                            f"frames' extent ({linked[2] - linked[0]:.4g} x {linked[3] - linked[1]:.4g} m; max "
                            f"{tol:.4g} m [publish] max_extent_growth_fraction, max_extent_growth_frames); not published")
    mc = links.get("map_candidates", 0)
    if mc:
        frac = links.get("map_accepted", 0) / mc
        if frac < cfg_pub["min_anchored_fraction"]:
            raise JobFailed(f"quality gate: only {frac:.1%} of the frames tried against the published map "
                            f"registered to it (min {cfg_pub['min_anchored_fraction']:.0%} "
                            "[publish] min_anchored_fraction); not published")


def build_routes(ws: Workspace, figures: dict) -> dict[str, Path]:
    """Route id -> route file of this build: the ``orp`` stage's output when that stage is in
    the build's report (``figures["stages"]``), else none (a reused workdir may hold an
    earlier build's routes: they are left out, with a warning)."""
    routes = ws.route_files()
    if "orp" in figures.get("stages", {}):
        return routes
    if routes:
        log.warning("publish: %s holds route panoramas (%s) of an earlier build; the orp stage is not part of "
                    "this one: not published", ws.routes_dir, ", ".join(routes))
    return {}


GEO_MATCH_M = 0.01  # two logs' origins closer than this (metres) are one origin


def geo_reference_of(logs) -> GeoReference | None:
    """The one geographic origin of ``logs`` (drive logs' ``[source]`` tables of
    import-geotagged: origin_latitude, origin_longitude), None when no log has one, or
    (warned) when some lack it or two origins differ by more than :data:`GEO_MATCH_M`
    (their frames are not one east/north plane)."""
    refs, without = [], []
    for lg in logs:
        src = (lg.meta or {}).get("source")
        if isinstance(src, dict) and "origin_latitude" in src and "origin_longitude" in src:
            try:
                refs.append((lg.log_id, GeoReference.from_attrs(src)))
            except ValueError as e:
                log.warning("publish: log %s: %s: the map gets no geo_reference", lg.log_id, e)
                return None
        else:
            without.append(lg.log_id)
    if not refs:
        return None
    if without:
        log.warning("publish: log(s) %s have no geographic origin while %s has: the map gets no geo_reference",
                    ", ".join(without), refs[0][0])
        return None
    first_id, first = refs[0]
    for log_id, ref in refs[1:]:
        d = float(np.hypot(*first.from_wgs84(ref.origin_latitude, ref.origin_longitude)))
        if d > GEO_MATCH_M:
            log.warning("publish: logs %s and %s have origins %.1f m apart (each is its own east/north plane): "
                        "the map gets no geo_reference", first_id, log_id, d)
            return None
    return first


def _record_geo(root: zarr.Group, geo: GeoReference | None, new_map: bool) -> bool:
    """Write ``geo`` as the map's geo_reference when this build creates the map; warn when
    the logs' origin does not match an existing map's. Returns whether it was written."""
    from mapstore.layout import read_geo_reference, write_geo_reference

    if geo is None:
        return False
    if new_map:
        write_geo_reference(root, geo)
        return True
    have = read_geo_reference(root)
    if have is None:
        log.warning("publish: the logs are geotagged but the map has no geographic reference: none recorded")
    else:
        x, y = have.from_wgs84(geo.origin_latitude, geo.origin_longitude)
        if float(np.hypot(x, y)) > GEO_MATCH_M:
            log.warning("publish: the logs' origin lies %.1f m from the map's geographic origin: their east/north "
                        "frame is not the map's", float(np.hypot(x, y)))
    return False


def _new_pose_rows(ws: Workspace, inputs: list[dict], version: int, source0: int) -> tuple[PoseTable, list[dict]]:
    from pipeline.stages.optimize import read_poses_table

    data = read_poses_table(ws.poses)  # log ids as text ("001" stays "001")
    data = data[~dropped_mask(ws.dropped, len(data))]  # dropped: not in the map
    names = data.dtype.names
    ids = [str(v) for v in data["log_id"]]
    index = {inp["log_id"]: source0 + k for k, inp in enumerate(inputs)}
    sigma = (np.column_stack([data["sigma_x"], data["sigma_y"], data["sigma_theta"]])
             if "sigma_x" in names else np.full((len(data), 3), np.nan))
    sources = [{"log_id": inp["log_id"], "path": inp["path"], "sha256": inp["sha256"],
                "frames": int(sum(i == inp["log_id"] for i in ids)), "version": version} for inp in inputs]
    table = PoseTable(
        np.column_stack([data["x"], data["y"], data["theta"]]), sigma, data["t"],
        np.array([index[i] for i in ids], np.int32), data["frame"].astype(np.int32),
        np.full(len(data), version, np.int32), [{}] * (source0 + len(inputs)))
    return table, sources


def _concat(old: PoseTable, new: PoseTable, new_sources: list[dict]) -> PoseTable:
    return PoseTable(np.vstack([old.pose, new.pose]), np.vstack([old.sigma, new.sigma]), np.r_[old.t, new.t],
                     np.r_[old.source, new.source], np.r_[old.frame, new.frame], np.r_[old.version, new.version],
                     list(old.sources) + new_sources)


def _copy_shards(dst: zarr.Group, src: zarr.Group, touched: dict, grid: MapGrid, spec) -> int:
    """Copy the touched shards of every array (levels, layers); returns shards written."""
    n = 0
    for k, shards in touched.items():
        shape = grid.level(int(k)).shape
        a_dst, a_src = dst[f"floor/{k}"], src[f"floor/{k}"]
        for ij in shards:
            r0, r1, c0, c1 = shard_box(tuple(ij), shape, spec.shard_px)
            a_dst[r0:r1, c0:c1] = a_src[r0:r1, c0:c1]
            n += 1
    cell, tile = spec.layer_cell_px, spec.chunk_px
    for name in ("coverage", "texture", "uniqueness", "updated"):
        f = tile if name == "updated" else cell
        a_dst, a_src = dst[f"{LAYERS_GROUP}/{name}"], src[f"{LAYERS_GROUP}/{name}"]
        for ij in touched["0"]:
            r0, r1, c0, c1 = shard_box(tuple(ij), grid.shape, spec.shard_px)
            sl = (slice(r0 // f, -(-r1 // f)), slice(c0 // f, -(-c1 // f)))
            a_dst[sl] = a_src[sl]
            n += 1
    return n


def run_publish(ws: Workspace, params: StageParams) -> dict:
    """Stage entry: gates, copy, commit, tag. Returns the report's ``publish`` section.

    From the build's context: the map repository, the version the build extends (``base``;
    for a map of routes only, no floor: ``route_base``, the version the build read its stored
    routes from, :func:`pipeline.stages.build.find_route_base`), the logs (their geographic origin,
    :func:`geo_reference_of`, is recorded when this build creates the map), the tag; the
    report so far (gates, the commit's key figures); this run's fingerprint (the commit's
    ``build``, by which a rerun finds itself already published)."""
    from mapstore.repository import MapRepository

    t0 = time.perf_counter()
    b = params.build
    map_url, base, route_base, tag, figures = b.map_url, b.base, b.route_base, b.tag, params.report
    inputs, build_id, geo = list(b.inputs), params.build_id, geo_reference_of(b.logs)
    pub = params.cfg["publish"]
    check_gates(figures, pub)
    branch = pub["branch"]
    touched_path = ws.touched
    has_floor = touched_path.is_file()
    routes = build_routes(ws, figures)
    if not has_floor and not routes:
        raise JobFailed(f"{ws.root}: nothing to publish (no rendered floor, no route panorama)")
    if has_floor:
        touched_info = json.loads(touched_path.read_text())
        grid = MapGrid.from_attrs(touched_info["grid"])
        version = int(touched_info["version"])
        staging = zarr.open_group(str(ws.render_store), mode="r")
    else:
        version = int((base or route_base or {"version": 0})["version"]) + 1
    with _publish_errors(map_url, branch):
        repo = MapRepository.open_or_create(map_url)
        with repo.commit_lock():
            tip = repo.branches().get(branch)
            if tip is not None:
                info = repo.repo.lookup_snapshot(tip)
                if (info.metadata or {}).get("build") == build_id:
                    log.info("publish: this build is already the tip of %s (%s)", branch, tip)
                    name = _ensure_tag(repo, tip, tag, pub, info.metadata.get("tag"))
                    return {"publish": {"snapshot": tip, "tag": name,
                                        "version": int(info.metadata.get("version", version)),
                                        "branch": branch, "resumed": True, "seconds": time.perf_counter() - t0}}
            read_from = base or route_base
            expected = None if read_from is None else read_from["snapshot"]
            if read_from is not None and tip != expected:
                raise JobFailed(f"{map_url}: branch {branch} moved to {tip} since this build read version "
                                f"{expected}; rerun the build to publish on top of it")
            if tip is None:
                repo.repo.create_branch(branch, repo.repo.lookup_branch("main"))
            session = repo.repo.writable_session(branch)
            root = zarr.open_group(session.store, mode="a")
            written, new = 0, PoseTable.empty()
            if has_floor:
                if base is None:
                    if "floor" in root:
                        raise JobFailed(f"{map_url}: branch {branch} already holds a map that this build did not start "
                                        "from; rerun the build to extend it")
                    create_floor(root, grid, read_floor(staging).spec, map_id=str(staging.attrs.get("map_id")))
                    old = PoseTable.empty()
                else:
                    if read_floor(root).grid != grid:
                        resize_floor(root, grid)
                    old = read_poses(root)
                written = _copy_shards(root, staging, touched_info["shards"], grid, read_floor(staging).spec)
                new, new_sources = _new_pose_rows(ws, inputs, version, len(old.sources))
                write_poses(root, _concat(old, new, new_sources))
                set_version(root, version)
            elif base is None and route_base is None:
                version = max([0] + _route_versions(root)) + 1  # a map of routes only
            elif "floor" in root:
                set_version(root, version)
            n_routes = _write_routes(root, routes, version)
            geo_written = _record_geo(root, geo, new_map=base is None and route_base is None)
            name = _new_tag(repo, tag, pub, branch)  # checked before the commit: no untagged version is left
            metadata = {
                "mosaicmap_version": __version__, "build": build_id, "build_key": b.build_key, "version": version,
                "tag": name,
                "logs": inputs, "config_hash": b.config_hash, "report": _key_figures(figures),
            }
            what = f"{len(new)} frames" + (f", routes {', '.join(routes)}" if routes else "")
            snapshot = session.commit(f"mosaicmap build: version {version}, {what} from "
                                      f"{', '.join(i['log_id'] for i in inputs)}", metadata=metadata)
            _ensure_tag(repo, snapshot, tag, pub, name)
    return {"publish": {"snapshot": snapshot, "tag": name, "version": version, "branch": branch,
                        "shards_written": written, "frames_added": len(new), "routes_written": n_routes,
                        "geo_reference": geo.to_attrs() if geo_written else None,
                        "resumed": False, "seconds": time.perf_counter() - t0}}


@contextmanager
def _publish_errors(map_url: str, branch: str) -> Iterator[None]:
    """The map store's failures during publish as one line, exit 1: another build committed
    on the branch first (icechunk's ConflictError: the branch moved under this commit; the
    commit is refused whole), or the store cannot be used any more (endpoint gone,
    credentials refused)."""
    import icechunk

    from mapstore.repository import StorageError, icechunk_message, storage_error

    try:
        yield
    except icechunk.ConflictError:
        raise JobFailed(f"{map_url}: another build published on branch {branch} while this one was publishing; "
                        "nothing of this build was published: rerun the build to publish on top of it") from None
    except StorageError as e:
        raise JobFailed(f"{map_url}: {e}") from None
    except icechunk.IcechunkError as e:
        err = storage_error(map_url, e)
        raise JobFailed(f"{map_url}: {err if err is not None else icechunk_message(e)}") from None


def _route_versions(root: zarr.Group) -> list[int]:
    from mapstore.routes import list_routes, route_attrs

    return [int(route_attrs(root, rid).get("version", 0)) for rid in list_routes(root)]


def _write_routes(root: zarr.Group, routes: dict[str, Path], version: int) -> int:
    """Write the build's routes (``/routes/<id>``) at publish ``version``; new sources get it."""
    from mapstore.routes import write_route
    from pipeline.stages.orp import read_route_file

    for rid, path in routes.items():
        rec, fig = read_route_file(path)
        rec.version = version
        rec.sources = [{**s, "version": version if s.get("version") is None else s["version"]} for s in rec.sources]
        rec.meta = {**rec.meta, "build": {k: fig[k] for k in ("runs", "rows", "length_m", "rows_fed") if k in fig}}
        if "ground_truth" in fig:
            rec.meta["build"]["ground_truth"] = fig["ground_truth"]
        write_route(root, rid, rec)
    return len(routes)


def _new_tag(repo, tag: str | None, pub: dict, branch: str) -> str:
    """The tag the commit about to be made gets (``tag``, else the next of ``[publish]
    tag_format``), checked while the commit lock is held: BadInput when it is invalid,
    exists or names a branch."""
    try:
        return repo.check_new_tag(tag or repo.next_tag(pub["tag_format"]), branches=(branch,))
    except ValueError as e:
        raise BadInput("--tag" if tag else "config[publish.tag_format]", str(e)) from None


def _ensure_tag(repo, snapshot: str, tag: str | None, pub: dict, wanted: str | None) -> str:
    name = tag or wanted or repo.next_tag(pub["tag_format"])
    existing = repo.tags().get(name)
    if existing is None:
        repo.tag(snapshot, name)
    elif existing != snapshot:
        raise JobFailed(f"tag {name} already names another version; choose another --tag")
    return name


def _key_figures(report: dict) -> dict:
    """The figures a commit carries (what `mosaicmap log` shows)."""
    out = {}
    for section, keys in (("links", ("candidates", "accepted", "map_accepted")),
                          ("optimization", ("frames", "residual_rms_px")),
                          ("ground_truth", ("pose_rms_px", "pose_max_px")),
                          ("render", ("shards", "level0_mpix", "mpix_per_s")),
                          ("orp", ("runs", "rows", "length_m", "bytes_per_km"))):
        for k in keys:
            v = report.get(section, {}).get(k)
            if v is not None:
                out.setdefault(section, {})[k] = v
    return out


STAGE = Stage("publish", run_publish, params_tables=("publish",), reads_base=True, needs_map=True, publishes=True)
