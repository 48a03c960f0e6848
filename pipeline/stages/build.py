"""The build orchestrator: runs the pipeline's stages in order over a work directory.

Each stage writes ``WORKDIR/<stage>/`` under a temporary name and renames it into place
with its ``manifest.json`` (input fingerprint, config hash, counts, timing) inside, so a
stage directory either is complete or does not exist. A rerun skips every stage whose
manifest matches its inputs and configuration; a killed run resumes at the first stage
that had not finished. A lock file keeps two builds out of one work directory.

Every stage is ``run(ws, params) -> report sections`` (:mod:`pipeline.stages.stage`): ``ws``
the work directory's :class:`~pipeline.stages.workspace.Workspace` (the one owner of its
paths), ``params`` the configuration tables the stage declares and the typed
:class:`~pipeline.stages.stage.BuildContext`. A stage's cache fingerprint is derived from
its declaration (:func:`stage_fingerprint`), so a knob re-runs exactly the stages whose
tables hold it (and those downstream of them).
"""

from __future__ import annotations

import fcntl
import json
import logging
import resource
import time
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterator

from pipeline import __version__
from pipeline.allocator import return_freed_memory
from pipeline.config import check_config, config_hash
from pipeline.errors import BadInput, JobFailed, writing
from pipeline.fsutil import atomic_dir, remove_stale_temps, sha256_files, write_json_atomic
from pipeline.progress import activity
from pipeline.stages import ingest, optimize, orp, publish, register, render
from pipeline.stages.publish import check_gates
from pipeline.stages.stage import BuildContext, Stage, config_tables, fingerprint_tables, process_cpu_seconds
from pipeline.stages.workspace import Workspace

log = logging.getLogger(__name__)

# Bumped by hand when the format inside a stage's output files or its manifest changes (a
# column added to poses.csv, a new array in the frames store): older stage outputs rerun.
# A renamed, added or removed output file needs no bump: the stage's declared outputs
# (pipeline.stages.workspace.OUTPUTS) are part of its fingerprint. The formats themselves
# cannot be derived from the names: hence this number.
LAYOUT_VERSION = 2


# The stages in build order (each declared in its module: its entry, the configuration
# tables it reads, how it depends on the published map; pipeline.stages.stage.Stage).
STAGES: dict[str, Stage] = {s.name: s for s in (ingest.STAGE, orp.STAGE, register.STAGE, optimize.STAGE,
                                                 render.STAGE, publish.STAGE)}
# Stages that need a map repository (--map); without one the build stops before them.
MAP_STAGES = tuple(name for name, s in STAGES.items() if s.needs_map)
# Stages that run only for some logs: the route panoramas (omni logs). Added when a log is
# omni (whatever [build] stages says), dropped otherwise: right after optimize when the build
# optimizes floor frames and [orp] floor_poses is on (the routes then start from the floor's
# optimized poses of the same frames), else right after ingest. Their output feeds publish
# only: the stages after them keep the previous stage's fingerprint as their upstream.
SIDE_STAGES = tuple(name for name, s in STAGES.items() if s.side)


def stage_fingerprint(stage: Stage, cfg: dict, upstream: str, ctx: BuildContext, side: dict[str, str]) -> str:
    """The cache key of ``stage`` in this build: what its output is a function of. The
    upstream stage's fingerprint (or the inputs'), the configuration tables the stage
    declares (:attr:`Stage.params_tables`: all it is given; their scheduler and worker
    counts left out: :func:`fingerprint_tables`), the mosaicmap version, the layout
    version and the names of the files it writes (:attr:`Stage.outputs`), the published
    version it extends (``reads_base``), the route base (``side``), the map URL and the side
    stages' fingerprints (``publishes``)."""
    return config_hash(
        {"upstream": upstream, "config": fingerprint_tables(cfg, stage.params_tables), "version": __version__,
         "layout": LAYOUT_VERSION, "outputs": list(stage.outputs),
         **({"base": ctx.base} if stage.reads_base and ctx.base else {}),
         **({"route_base": ctx.route_base} if stage.side and ctx.route_base else {}),
         **({"map": ctx.map_url, **({"side": side} if side else {})} if stage.publishes else {})}
    )


def _with_orp(configured: list[str], logs, floor_poses: bool = True) -> list[str]:
    """``configured`` with ``orp`` after ``optimize`` (``floor_poses``) or ``ingest`` when a
    log is omni, without it otherwise."""
    out = [s for s in configured if s != "orp"]
    if any(lg.camera.is_omni for lg in logs) and "ingest" in out:
        after = "optimize" if floor_poses and "optimize" in out else "ingest"
        out.insert(out.index(after) + 1, "orp")
    return out


def _refuse_logs_in_map(base: dict, inputs: list[dict], logs) -> None:
    """A log already in the map (same checksum) would enter it twice: bad input."""
    import zarr

    from mapstore.layout import read_poses
    from mapstore.repository import MapRepository
    from mapstore.routes import list_routes, route_attrs

    root = zarr.open_group(MapRepository.open(base["url"]).readonly(base["snapshot"]).store, mode="r")
    known = {src.get("sha256"): src for src in read_poses(root).sources} if "floor" in root else {}
    for rid in list_routes(root):  # logs merged into a route panorama
        known.update({src.get("sha256"): src for src in route_attrs(root, rid).get("sources", [])})
    for inp, lg in zip(inputs, logs):
        src = known.get(inp["sha256"])
        if src is not None:
            raise BadInput(lg.path, f"already in the map {base['url']} (added by version {src.get('version')} "
                                    f"as log {src.get('log_id')}, same checksum); nothing to add")


@contextmanager
def map_storage(map_url: str | None) -> Iterator[None]:
    """A map repository whose store cannot be used (S3 endpoint unreachable, credentials
    refused, no such bucket: :class:`mapstore.repository.StorageError`) is bad input: one
    line naming the URL and what to check, exit 2."""
    from mapstore.repository import StorageError

    try:
        yield
    except StorageError as e:
        raise BadInput(map_url or "--map", str(e)) from None


def _tip_root(map_url: str | None, branch: str, build_key: str = ""):
    """``(snapshot, zarr root)`` of the version a build extends, or None (no repository, no
    branch, no commit). When the tip is this very build's commit (same ``build_key``: a rerun
    after publishing, or a publish killed before its stage finished) it is the tip's parent,
    so the build's stages stay up to date and publish finds itself already done."""
    if map_url is None:
        return None
    import zarr

    from mapstore.repository import MapRepository, StorageError

    try:
        repo = MapRepository.open(map_url)
    except StorageError:
        raise  # (the map may well be there: the store cannot be asked)
    except ValueError:
        return None
    if branch not in repo.repo.list_branches():
        return None
    snapshot = repo.repo.lookup_branch(branch)
    if build_key and (repo.repo.lookup_snapshot(snapshot).metadata or {}).get("build_key") == build_key:
        history = list(repo.repo.ancestry(snapshot_id=snapshot))
        if len(history) < 2:
            return None
        snapshot = history[1].id
    try:
        return snapshot, zarr.open_group(repo.readonly(snapshot).store, mode="r")
    except zarr.errors.GroupNotFoundError:  # a repository with no commit yet
        return None


def check_build_tag(map_url: str | None, tag: str | None, branch: str, build_key: str) -> None:
    """Refuse ``build --tag`` before any stage runs (so that no commit is left untagged): an
    invalid name (:func:`mapstore.repository.check_tag_name`: control characters, length, ...),
    a branch's name, or a tag that exists already, unless it names this very build's commit (a
    rerun after publishing). :class:`BadInput` naming ``--tag``."""
    if tag is None:
        return
    from mapstore.repository import MapRepository, check_tag_name

    try:
        check_tag_name(tag)
    except ValueError as e:
        raise BadInput("--tag", str(e)) from None
    if tag == branch:
        raise BadInput("--tag", f"tag name {tag!r} is the name of the branch the build publishes on")
    if map_url is None or not MapRepository.exists(map_url):
        return
    repo = MapRepository.open(map_url)
    tags = repo.tags()
    if tag in tags:
        meta = repo.repo.lookup_snapshot(tags[tag]).metadata or {}
        if meta.get("build_key") != build_key:
            raise BadInput("--tag", f"tag {tag!r} exists already (at {tags[tag]}); choose another --tag")
    elif tag in repo.branches():
        raise BadInput("--tag", f"tag name {tag!r} is the name of a branch (a tag would shadow it)")


def find_base(map_url: str | None, branch: str, build_key: str = "") -> dict | None:
    """The published version a build extends: ``{"url", "snapshot", "version"}`` of the
    branch tip when the repository exists and holds a map (a floor), else None (see
    :func:`_tip_root` for a rerun of a published build)."""
    from mapstore.layout import read_floor

    tip = _tip_root(map_url, branch, build_key)
    if tip is None or "floor" not in tip[1]:
        return None
    try:
        info = read_floor(tip[1])
    except ValueError as e:
        raise BadInput(map_url, f"not a usable mosaicmap map: {e}") from None
    return {"url": map_url, "snapshot": tip[0], "version": info.version, "pixel_size": info.grid.pixel_size}


def find_route_base(map_url: str | None, branch: str, build_key: str = "") -> dict | None:
    """For a map holding route panoramas but no floor (an omni build without floor frames):
    ``{"url", "snapshot", "version"}`` (version: the routes' highest), else None. The orp stage
    refreshes the stored routes from it; the floor stages never see it."""
    from mapstore.routes import ROUTES_GROUP, list_routes, route_attrs

    tip = _tip_root(map_url, branch, build_key)
    if tip is None or "floor" in tip[1] or ROUTES_GROUP not in tip[1]:
        return None
    versions = [int(route_attrs(tip[1], rid).get("version", 0)) for rid in list_routes(tip[1])]
    return {"url": map_url, "snapshot": tip[0], "version": max(versions, default=0)}


def with_map_pixel_size(cfg: dict, logs: list, base: dict | None) -> dict:
    """``cfg`` with ``[map] pixel_size_m`` resolved: as configured when positive; with 0
    (the default, "auto") the published map's when the build extends one, else the finest
    native ground pixel of the logs (a rectified log's ``pixel_size_m``, ``height_m / f`` of a
    downward camera at its principal point along its coarser axis, an omni camera's ground
    pixel over its floor annulus)."""
    px = float(cfg["map"]["pixel_size_m"])
    if px < 0:
        raise BadInput("config[map.pixel_size_m]", f"must be positive, or 0 for automatic, got {px}")
    if px > 0:
        return cfg
    if base is not None and base.get("pixel_size"):
        px = float(base["pixel_size"])
    else:
        px = min(native_ground_pixel(lg, cfg) for lg in logs)
    out = dict(cfg)
    out["map"] = {**cfg["map"], "pixel_size_m": px}
    return out


def native_ground_pixel(lg, cfg: dict) -> float:
    """A log's native ground pixel (metres; see :func:`with_map_pixel_size`)."""
    cam = lg.camera
    if cam.is_omni:
        from pipeline.omni_ingest import OmniFloorParams, floor_annulus

        try:
            return floor_annulus(cam.omni, 0.0, OmniFloorParams.from_config(cfg["omni"])).ground_pixel_m
        except ValueError as e:
            raise BadInput(lg.path / "drive.toml[camera]", f"log {lg.log_id}: {e} (see configs/omni.toml [omni])") from None
    return float(max(cam.ground_pixel_size))  # the coarser axis: nothing is upsampled


def default_workdir(log_paths: list[Path]) -> Path:
    """``.mosaicmap-work/<hash>`` in the current directory, one per set of logs."""
    key = config_hash(sorted(str(Path(p).resolve()) for p in log_paths))[:12]
    return Path(".mosaicmap-work") / key


@contextmanager
def workdir_lock(ws: Workspace) -> Iterator[None]:
    """Hold the work directory's lock (JobFailed when another build holds it); what a killed
    build left under temporary names (``.tmp-<stage>-*``) is removed once the lock is held."""
    with writing("the work directory", ws.root):
        ws.root.mkdir(parents=True, exist_ok=True)
        f = open(ws.lock_file, "w")
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise JobFailed(f"{ws.root}: another build is running in this work directory") from None
        for p in remove_stale_temps(ws.root):
            log.info("removed %s, left by an interrupted build", p)
        yield


def read_manifest(ws: Workspace, stage: str) -> dict | None:
    """The finished ``stage``'s manifest, or None (not run, or cut short)."""
    try:
        return json.loads(ws.manifest(stage).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _peak_rss_mb() -> float:
    """This process's peak resident set so far, MB (Linux reports ``ru_maxrss`` in KiB).
    Read at the end of each stage, the stage whose figure first exceeds the previous one's
    set the build's peak."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_build(
    log_paths: list[Path],
    workdir: Path,
    cfg: dict,
    *,
    until: str | None = None,
    only: str | None = None,
    quiet: bool = False,
    map_url: str | None = None,
    tag: str | None = None,
    on_stage: Callable[[str, dict], None] | None = None,
) -> dict:
    """Run the stages (all, up to ``until``, or ``only`` one) and return the report dict.

    With ``map_url`` (a map repository: a local directory or ``s3://bucket/prefix``) the
    build renders and publishes a new version of it (tagged ``tag`` or by the configured
    format), extending the published map when it exists; without it, it stops after
    ``optimize``. ``cfg`` is checked against the schema first (:func:`pipeline.config.check_config`):
    values a command line or a caller set after :func:`pipeline.config.load_config` (e.g.
    ``--scheduler``) meet the same rules.

    ``on_stage(name, report)`` is called as each stage finishes (run or skipped), with the
    report so far (its sections merged): the command line prints the stage's line then.
    While a stage runs without progress of its own, :func:`pipeline.progress.activity`
    prints that it is working (unless ``quiet``).
    """
    check_config(cfg, lambda table, key: "configuration (after command-line options)")
    t0 = time.perf_counter()
    logs = ingest.load_logs(log_paths, cfg)
    configured = _with_orp(list(cfg["build"]["stages"]), logs, cfg["orp"]["floor_poses"])
    for name in configured:
        if name not in STAGES:
            raise BadInput("config[build.stages]", f"unknown stage {name!r} (known: {', '.join(STAGES)})")
    if until is not None and until not in configured:
        raise BadInput("--until", f"unknown stage {until!r} (stages: {', '.join(configured)})")
    if map_url is None:
        if until in MAP_STAGES or only in MAP_STAGES:
            raise BadInput("--map", f"stage {until or only} needs a map repository (--map REPO)")
        configured = [s for s in configured if s not in MAP_STAGES]
    stages = configured[: configured.index(until) + 1] if until else list(configured)
    if only is not None:
        stages = [only]

    inputs = [{"log_id": lg.log_id, "path": str(lg.path.resolve()), "sha256": sha256_files(lg.files())} for lg in logs]
    report: dict = {
        "mosaicmap_version": __version__,
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "workdir": str(workdir),
        "logs": inputs,
        "stages": {},
    }
    build_key = config_hash({"inputs": inputs, "config": cfg, "version": __version__})
    with map_storage(map_url):
        check_build_tag(map_url, tag, cfg["publish"]["branch"], build_key)
        base = find_base(map_url, cfg["publish"]["branch"], build_key)
        route_base = base if base is not None else find_route_base(map_url, cfg["publish"]["branch"], build_key)
    if route_base is not None:
        _refuse_logs_in_map(route_base, inputs, logs)
    if map_url is not None:
        report["map"] = {"url": map_url, "base_snapshot": None if base is None else base["snapshot"],
                         "base_version": 0 if base is None else base["version"]}
    cfg = with_map_pixel_size(cfg, logs, base)
    report["map_pixel_size_m"] = cfg["map"]["pixel_size_m"]
    ctx = BuildContext(logs=tuple(logs), inputs=tuple(inputs), map_url=map_url, branch=cfg["publish"]["branch"],
                       tag=tag, base=base, route_base=route_base, build_key=build_key, config_hash=config_hash(cfg),
                       quiet=quiet)
    ws = Workspace(workdir)
    upstream = config_hash(inputs)
    side: dict[str, str] = {}  # side stage -> its fingerprint (publish depends on it)
    with workdir_lock(ws):
        for name in stages:
            stage = STAGES[name]
            fingerprint = stage_fingerprint(stage, cfg, upstream, ctx, side)
            manifest = read_manifest(ws, name)
            if manifest is not None and manifest.get("fingerprint") == fingerprint:
                log.info("%s: up to date, skipped", name)
                report["stages"][name] = {"skipped": True, "seconds": 0.0, "cpu_seconds": 0.0}
                sections = manifest["counts"]
            else:
                t_stage, cpu_stage = time.perf_counter(), process_cpu_seconds()
                what = ("the map repository", map_url) if stage.publishes else ("the work directory", ws.root)
                with activity(name, quiet=quiet), writing(*what), atomic_dir(ws.stage_dir(name), replace=True) as tmp:
                    if stage.gated:
                        check_gates(report, cfg["publish"])  # a failing build stops before rendering
                    stage_ws = ws.writing(name, tmp)
                    sections = stage.run(stage_ws, stage.params(cfg, ctx, report, fingerprint))
                    seconds, cpu = time.perf_counter() - t_stage, process_cpu_seconds() - cpu_stage
                    write_json_atomic(
                        stage_ws.manifest(name),
                        {
                            "stage": name,
                            "fingerprint": fingerprint,
                            "upstream": upstream,
                            "config_hash": config_hash(config_tables(cfg, stage.params_tables)),
                            "mosaicmap_version": __version__,
                            "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                            "seconds": seconds,
                            "cpu_seconds": cpu,
                            "counts": sections,
                        },
                    )
                report["stages"][name] = {"skipped": False, "seconds": seconds, "cpu_seconds": cpu,
                                          "peak_rss_mb": round(_peak_rss_mb(), 1)}
                return_freed_memory()  # (after a stage that ran; a skipped one freed nothing)
            for key, section in sections.items():
                report.setdefault(key, {}).update(section)
            if stage.after is not None:
                with writing("the work directory", ws.root):
                    stage.after(ws)
            if stage.side:
                side[name] = fingerprint
            else:
                upstream = fingerprint
            if on_stage is not None:
                on_stage(name, report)
    report["seconds_total"] = time.perf_counter() - t0
    return report
