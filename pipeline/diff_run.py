"""What ``mosaicmap diff`` runs (the command, :mod:`pipeline.cli.diff`, is its options):
:func:`diff_versions` compares two versions of a map and writes the outputs, the command
prints :func:`diff_summary_lines` of it.

The work is in :mod:`mapstore.diff` (tiles, regions, impact, route panoramas) and
:mod:`mapstore.change_detect` (pixels); the report and the files of ``out_dir`` in
:mod:`pipeline.diff_report` (which documents every report key); the comparison with a
simulator's change mask (``truth``) in :mod:`pipeline.evaluate`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from mapstore.diff import DiffResult
from pipeline.errors import BadInput
from pipeline.map_version import open_version

__all__ = ["DiffRun", "diff_versions", "diff_summary_lines"]

DEFAULT_CONFIG_NAME = "configs/diff.toml"  # named in a config error when no --config file was given


@dataclass(frozen=True)
class DiffRun:
    """A diff as run: ``report`` (the JSON report, :func:`pipeline.diff_report.report_dict`,
    with ``outputs`` and the timings, seconds) and ``result`` (what it was made of)."""

    report: dict
    result: DiffResult

    @property
    def regions(self) -> int:
        """Number of changed regions found."""
        return len(self.result.regions)


def diff_versions(repo: str, from_version: str, to_version: str, *, cfg: dict, out_dir: Path | None = None,
                  truth: Path | None = None, config_file: Path | None = None,
                  started: float | None = None) -> DiffRun:
    """Changes of the floor (and the route panoramas) between versions ``from_version`` and
    ``to_version`` of the map in ``repo``.

    Args:
        repo: the map repository's URL (directory, ``file://``, ``s3://``).
        from_version, to_version: versions (tag, snapshot id or unique prefix, branch,
            ``latest``); FROM must be an ancestor of TO.
        cfg: the effective configuration (its ``[diff]`` table: detection, ``[diff.routes]``,
            ``[diff.report]`` images, ``[diff.truth]``).
        out_dir: write ``diff.json``, the regions, ``overlay.png``, the route figures and
            ``diff.html`` there (:func:`pipeline.diff_report.write_outputs`).
        truth: a simulator's change mask (``changes.png`` with ``grid.json`` and
            ``changes.json`` beside it): the report adds ``truth``.
        config_file: the file ``cfg`` came from (named when ``[diff]`` is inconsistent).
        started: :func:`time.perf_counter` when the command started (default now): the
            report's ``seconds.command`` counts from it.

    BadInput (exit code 2) naming the repository, the version, the truth file, the config or
    the output that cannot be written.
    """
    from mapstore.diff import DiffParams, diff_maps, is_ancestor
    from mapstore.layout import read_poses
    from pipeline.config import config_hash
    from pipeline.diff_report import report_dict, write_outputs, write_report_file
    from pipeline.evaluate import evaluate_diff, map_world_alignment, read_truth_mask

    t0 = time.perf_counter() if started is None else started
    _, sid_from, root_from, info_from = open_version(repo, from_version, routes_only_ok=True)
    mrepo, sid_to, root_to, info_to = open_version(repo, to_version, routes_only_ok=True)
    for version, sid, info in ((from_version, sid_from, info_from), (to_version, sid_to, info_to)):
        if info is None:
            raise BadInput(repo, f"version {version} ({sid}) holds route panoramas only, no floor: diff compares "
                                 "versions of a map with a floor (routes-only maps are not supported yet)")
    truth_mask = read_truth_mask(truth) if truth is not None else None
    if not is_ancestor(mrepo, sid_from, sid_to):
        raise BadInput(repo, f"FROM {from_version} ({sid_from}) is not an ancestor of TO {to_version} ({sid_to}): "
                             "diff an older version against a newer one of the same history")
    try:
        params = DiffParams.from_config(cfg["diff"], info_to.grid.pixel_size)
    except ValueError as e:
        raise BadInput(config_file or DEFAULT_CONFIG_NAME, str(e)) from None
    try:
        result = diff_maps(mrepo, sid_from, sid_to, params, from_root=root_from, to_root=root_to)
    except ValueError as e:
        raise BadInput(repo, str(e)) from None
    truth_dict = None
    if truth_mask is not None:
        t = time.perf_counter()
        alignment = map_world_alignment(read_poses(root_to))
        tcfg = cfg["diff"]["truth"]
        truth_dict = evaluate_diff(result, truth_mask, alignment, min_observed_fraction=tcfg["min_observed_fraction"],
                                   min_recall=tcfg["min_recall"]).to_dict()
        truth_dict["mask"] = str(truth)
        result.seconds["truth"] = time.perf_counter() - t
    rep = report_dict(result, repository=repo, from_version=from_version, to_version=to_version,
                      map_id=info_to.map_id, truth=truth_dict,
                      params={"config_hash": config_hash(cfg["diff"]), "diff": cfg["diff"]},
                      route_profile=params.routes.profile)
    try:
        if out_dir is not None:
            t = time.perf_counter()
            write_outputs(out_dir, rep, result, root_from, root_to, info_to.levels, cfg["diff"]["report"],
                          info_to.map_id)
            rep["seconds"]["outputs"] = round(time.perf_counter() - t, 4)
        rep["seconds"]["command"] = round(time.perf_counter() - t0, 4)
        if out_dir is not None:
            write_report_file(out_dir, rep)
    except OSError as e:
        raise BadInput(e.filename or out_dir, f"cannot write: {e.strerror or e}") from None
    return DiffRun(rep, result)


def diff_summary_lines(run: DiffRun) -> list[str]:
    """What ``mosaicmap diff`` prints: the report's summary
    (:func:`pipeline.diff_report.summary_lines`), the outputs written and the timings."""
    from pipeline.diff_report import summary_lines

    rep = run.report
    lines = summary_lines(rep)
    if "outputs" in rep:
        lines.append(f"outputs: {', '.join(rep['outputs'].values())}")
    lines.append(f"seconds: {rep['seconds']['command']:.2f} (diff {run.result.seconds['total']:.2f})")
    return lines
