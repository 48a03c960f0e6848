"""The build orchestrator: runs the pipeline's stages in order over a work directory.

Each stage writes ``WORKDIR/<stage>/`` under a temporary name and renames it into place
with its ``manifest.json`` (input fingerprint, config hash, counts, timing) inside, so a
stage directory either is complete or does not exist. A rerun skips every stage whose
manifest matches its inputs and configuration; a killed run resumes at the first stage
that had not finished. A lock file keeps two builds out of one work directory.
"""

from __future__ import annotations

import fcntl
import json
import logging
import time
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterator

from pipeline import __version__
from pipeline.config import config_hash
from pipeline.errors import BadInput, JobFailed
from pipeline.fsutil import atomic_dir, sha256_files, write_json_atomic, write_text_atomic

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
# Bumped when a stage's output or manifest layout changes: older stage outputs rerun.
LAYOUT_VERSION = 1


def _run_ingest(ctx: dict, out_dir: Path) -> dict:
    from pipeline.ingest import run_ingest

    return {"ingest": run_ingest(ctx["logs"], out_dir, ctx["cfg"], quiet=ctx["quiet"])}


def _run_register(ctx: dict, out_dir: Path) -> dict:
    from pipeline.register import run_register

    counts = run_register(ctx["workdir"], out_dir, ctx["cfg"], quiet=ctx["quiet"])
    return {
        "links": {k: counts[k] for k in ("candidates", "accepted", "rejected")},
        "registration": counts,
    }


def _run_optimize(ctx: dict, out_dir: Path) -> dict:
    from pipeline.optimize_stage import run_optimize

    return run_optimize(ctx["workdir"], out_dir, ctx["cfg"], quiet=ctx["quiet"])


def _publish_optimize(ctx: dict, stage_dir: Path) -> None:
    """The optimized trajectory and links also go to WORKDIR/poses.csv and WORKDIR/links.csv."""
    for name in ("poses.csv", "links.csv"):
        write_text_atomic(ctx["workdir"] / name, (stage_dir / name).read_text())


# Stage name -> (function(ctx, out_dir) -> report sections, config tables the stage
# depends on, hook run after the stage is done or found up to date). Later issues append
# render and publish.
STAGES: dict[str, tuple[Callable[[dict, Path], dict], tuple[str, ...], Callable | None]] = {
    "ingest": (_run_ingest, ("map", "ingest"), None),
    "register": (_run_register, ("register", "optimize"), None),
    "optimize": (_run_optimize, ("optimize",), _publish_optimize),
}


@contextmanager
def workdir_lock(workdir: Path) -> Iterator[None]:
    workdir.mkdir(parents=True, exist_ok=True)
    with open(workdir / ".lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise JobFailed(f"{workdir}: another build is running in this work directory") from None
        yield


def read_manifest(stage_dir: Path) -> dict | None:
    try:
        return json.loads((stage_dir / MANIFEST).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def run_build(
    log_paths: list[Path],
    workdir: Path,
    cfg: dict,
    *,
    until: str | None = None,
    only: str | None = None,
    quiet: bool = False,
) -> dict:
    """Run the stages (all, up to ``until``, or ``only`` one) and return the report dict."""
    from pipeline.ingest import load_logs

    configured = cfg["build"]["stages"]
    for name in configured:
        if name not in STAGES:
            raise BadInput("config[build.stages]", f"unknown stage {name!r} (known: {', '.join(STAGES)})")
    if until is not None and until not in configured:
        raise BadInput("--until", f"unknown stage {until!r} (stages: {', '.join(configured)})")
    stages = configured[: configured.index(until) + 1] if until else list(configured)
    if only is not None:
        stages = [only]

    t0 = time.perf_counter()
    logs = load_logs(log_paths, cfg)
    inputs = [{"log_id": lg.log_id, "path": str(lg.path.resolve()), "sha256": sha256_files(lg.files())} for lg in logs]
    report: dict = {
        "mosaicmap_version": __version__,
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "workdir": str(workdir),
        "logs": inputs,
        "stages": {},
    }
    ctx = {"logs": logs, "cfg": cfg, "quiet": quiet, "workdir": workdir}
    upstream = config_hash(inputs)
    with workdir_lock(workdir):
        for name in stages:
            fn, tables, after = STAGES[name]
            fingerprint = config_hash(
                {"upstream": upstream, "config": {t: cfg[t] for t in tables}, "version": __version__,
                 "layout": LAYOUT_VERSION}
            )
            stage_dir = workdir / name
            manifest = read_manifest(stage_dir)
            if manifest is not None and manifest.get("fingerprint") == fingerprint:
                log.info("%s: up to date, skipped", name)
                report["stages"][name] = {"skipped": True, "seconds": 0.0}
                sections = manifest["counts"]
            else:
                t_stage = time.perf_counter()
                with atomic_dir(stage_dir, replace=True) as tmp:
                    sections = fn(ctx, tmp)
                    seconds = time.perf_counter() - t_stage
                    write_json_atomic(
                        tmp / MANIFEST,
                        {
                            "stage": name,
                            "fingerprint": fingerprint,
                            "upstream": upstream,
                            "config_hash": config_hash({t: cfg[t] for t in tables}),
                            "mosaicmap_version": __version__,
                            "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                            "seconds": seconds,
                            "counts": sections,
                        },
                    )
                report["stages"][name] = {"skipped": False, "seconds": seconds}
            for key, section in sections.items():
                report.setdefault(key, {}).update(section)
            if after is not None:
                after(ctx, stage_dir)
            upstream = fingerprint
    report["seconds_total"] = time.perf_counter() - t0
    return report
