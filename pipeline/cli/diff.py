"""Commands: diff (the diff half of the map tools).

``mosaicmap diff REPO FROM TO``: what changed on the floor between two versions of a map,
where (metres), how big, and whether it hurts localization there. The command parses its
options, calls :func:`pipeline.diff_run.diff_versions` (which documents the work and where
it lives), writes the report and prints :func:`pipeline.diff_run.diff_summary_lines`.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import config_option, quiet_option, report_option, setup, write_report
from pipeline.errors import BadInput, JobFailed


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

    from pipeline.diff_run import diff_summary_lines, diff_versions

    t0 = time.perf_counter()
    cfg = setup(config_file, quiet)
    run = diff_versions(repo, from_version, to_version, cfg=cfg, out_dir=out_dir, truth=truth,
                        config_file=config_file, started=t0)
    try:
        write_report(report, run.report)
    except OSError as e:
        raise BadInput(e.filename or out_dir or report, f"cannot write: {e.strerror or e}") from None
    click.echo("\n".join(diff_summary_lines(run)))
    if fail_on_change and run.regions:
        raise JobFailed(f"{run.regions} changed region(s) between {from_version} and {to_version} "
                        "(--fail-on-change)")
