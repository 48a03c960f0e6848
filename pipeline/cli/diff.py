"""Commands: diff (the diff half of the map tools).

``mosaicmap diff REPO FROM TO``: what changed on the floor between two versions of a map,
where (metres), how big, and whether it hurts localization there. The work is in
:mod:`mapstore.diff` (tiles, regions, impact) and :mod:`mapstore.change_detect` (pixels);
the outputs in :mod:`pipeline.diff_report`; ``--truth`` in :mod:`pipeline.evaluate`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click

from pipeline.cli.common import config_option, quiet_option, report_option, setup, write_report
from pipeline.errors import BadInput, JobFailed

log = logging.getLogger(__name__)


@click.command("diff")
@click.argument("repo")
@click.argument("from_version", metavar="FROM")
@click.argument("to_version", metavar="TO")
@click.option("--out", "-o", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Directory for diff.json (the report), the regions (regions.geojson in WGS 84 when the map "
                   "has a geographic reference, else regions.json in local metres), overlay.png and diff.html "
                   "(one self-contained page); existing files of these names are replaced.")
@report_option
@click.option("--fail-on-change", is_flag=True,
              help="Exit with code 1 when changed regions were found (after writing every output); "
                   "without it the exit code is 0 whether or not the floor changed.")
@click.option("--truth", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="MASK",
              help="A simulator's change mask (changes.png, with grid.json and changes.json beside it): "
                   "the report adds per-change detection, IoU, missed and unobserved changes and false regions.")
@config_option
@quiet_option
def diff_cmd(repo: str, from_version: str, to_version: str, out_dir: Path | None, report: Path | None,
             fail_on_change: bool, truth: Path | None, config_file: Path | None, quiet: bool) -> None:
    """Changes of the floor between versions FROM and TO of the map in REPO.

    FROM must be an ancestor of TO (an older version on the same history); a version is a
    tag, a snapshot id (or a unique prefix of 6+ characters), a branch or `latest`. Only
    the tiles TO rewrote are compared, so the cost follows the changed area, not the
    map's size. Illumination and exposure differences and sub-pixel misalignment are not
    changes; area TO covers for the first time is reported as new coverage. Prints the
    regions: area, centre (metres, the map's floor frame), contrast, texture and
    uniqueness before and after, and whether localization is at risk there. Route
    panoramas (/routes/<id>) are compared too: routes added, removed and changed, and for
    a changed route the path-length ranges (metres) and azimuth sectors (degrees) that
    changed and the largest move of its poses.

    Exit codes: 0 done (changes or not), 1 with --fail-on-change when regions were found,
    2 bad input (unknown version, FROM not an ancestor of TO, bad truth file, ...).
    """
    import time

    from mapstore.diff import DiffParams, diff_maps, is_ancestor
    from mapstore.layout import read_poses
    from pipeline.cli.map import _open_version
    from pipeline.config import config_hash
    from pipeline.diff_report import report_dict, summary_lines, write_outputs, write_report_file
    from pipeline.evaluate import evaluate_diff, map_world_alignment, read_truth_mask

    t0 = time.perf_counter()
    cfg = setup(config_file, quiet)
    _, sid_from, root_from, info_from = _open_version(repo, from_version)
    mrepo, sid_to, root_to, info_to = _open_version(repo, to_version)
    truth_mask = read_truth_mask(truth) if truth is not None else None
    if not is_ancestor(mrepo, sid_from, sid_to):
        raise BadInput(repo, f"FROM {from_version} ({sid_from}) is not an ancestor of TO {to_version} ({sid_to}): "
                             "diff an older version against a newer one of the same history")
    try:
        params = DiffParams.from_config(cfg["diff"], info_to.grid.pixel_size)
    except ValueError as e:
        raise BadInput(config_file or "configs/diff.toml", str(e)) from None
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
        write_report(report, rep)
    except OSError as e:
        raise BadInput(e.filename or out_dir or report, f"cannot write: {e.strerror or e}") from None
    lines = summary_lines(rep)
    if out_dir is not None:
        lines.append(f"outputs: {', '.join(rep['outputs'].values())}")
    lines.append(f"seconds: {rep['seconds']['command']:.2f} (diff {result.seconds['total']:.2f})")
    click.echo("\n".join(lines))
    if fail_on_change and result.regions:
        raise JobFailed(f"{len(result.regions)} changed region(s) between {from_version} and {to_version} "
                        "(--fail-on-change)")
