"""Print a short human summary of a build report (used by ``make demo``).

Usage: ``python -m pipeline.summary REPORT.json``
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def summarize(report: dict) -> list[str]:
    lines = [f"mosaicmap {report['mosaicmap_version']}: build of {len(report['logs'])} log(s) in {report['workdir']}"]
    for name, st in report["stages"].items():
        state = "up to date (skipped)" if st["skipped"] else f"{st['seconds']:.2f} s"
        lines.append(f"  {name:<10} {state}")
    ing = report.get("ingest")
    if ing:
        lines.append(
            f"  frames: {ing['frames_accepted']} accepted, {ing['frames_rejected']} rejected "
            f"of {ing['frames_total']} ({ing['frames_per_s']:.0f} frames/s)"
        )
        reasons: dict[str, int] = {}
        for r in ing["rejected"]:
            key = r["reason"].split(":")[0]
            reasons[key] = reasons.get(key, 0) + 1
        for key, n in sorted(reasons.items(), key=lambda kv: -kv[1]):
            lines.append(f"    rejected, {key}: {n}")
        for lg in ing["logs"]:
            ff = lg["flat_field"]
            lines.append(
                f"  log {lg['log_id']}: raw {lg['raw_shape'][1]}x{lg['raw_shape'][0]} -> rectified "
                f"{lg['rectified_shape'][1]}x{lg['rectified_shape'][0]}, flat field: {ff['source']}"
            )
    reg = report.get("registration")
    if reg:
        lines.append(
            f"  links: {reg['accepted']} of {reg['candidates']} candidate pairs registered "
            f"({reg['sequential_candidates']} sequential, {reg['revisit_candidates']} revisits; "
            f"{reg['pairs_per_s']:.0f} pairs/s)"
        )
        for key, n in reg["rejection_reasons"].items():
            lines.append(f"    not registered, {key}: {n}")
    opt = report.get("optimization")
    if opt:
        links = report["links"]
        lines.append(
            f"  optimization: {opt['frames']} poses in {opt['seconds']:.2f} s, {links['rejected_outliers']} outlier "
            f"links rejected, residual RMS {opt['residual_rms_px']:.4f} px (max {opt['residual_max_px']:.4f} px)"
        )
    geo = report.get("geometry")
    if geo and geo.get("frames_dropped"):
        lines.append(f"  dropped (a wild prior, no accepted link; not rendered, not published): "
                     f"{geo['frames_dropped']} frames")
        for d in geo["dropped"][:5]:
            lines.append(f"    {d['log']} frame {d['frame']}: {d['reason']}")
    gt = report.get("ground_truth")
    if gt:
        lines.append(
            f"  vs ground truth: poses RMS {gt['pose_rms_px']:.3f} px, max {gt['pose_max_px']:.3f} px "
            f"(odometry alone: RMS {gt['odometry_rms_px']:.1f} px); links median {gt['link_error_median_px']:.4f} px, "
            f"p95 {gt['link_error_p95_px']:.4f} px"
        )
    if report.get("links", {}).get("map_candidates"):
        links = report["links"]
        lines.append(f"  anchored to the published map: {links['map_accepted']} of {links['map_candidates']} "
                     "frames tried registered to it")
    ren = report.get("render")
    if ren:
        lines.append(
            f"  render: {ren['shards']} shards, {ren['level0_mpix']:.1f} MPix at level 0 ({ren['covered_mpix']:.1f} "
            f"covered) + {ren['levels'] - 1} pyramid levels, {ren['mpix_per_s']:.0f} MPix/s; exposure gains "
            f"{ren['gain_min']:.3f}..{ren['gain_max']:.3f}"
        )
    orp = report.get("orp")
    if orp:
        reg = orp.get("registration", {})
        lines.append(
            f"  route panoramas: {orp['routes'] if isinstance(orp['routes'], int) else len(orp['routes'])} route(s) "
            f"from {orp['runs']} run(s), {orp['rows']} rows, {orp['length_m']:.1f} m; "
            f"{reg.get('fixes_accepted', 0)} of {reg.get('fixes_tried', 0)} cross-run fixes, "
            f"{reg.get('loop_closures', 0)} loop closures; poses from {orp.get('priors', '?')}")
        ogt = orp.get("ground_truth")
        if ogt:
            lines.append(f"    route poses vs ground truth: RMS {100 * ogt['pose_rms_m']:.2f} cm, max "
                         f"{100 * ogt['pose_max_m']:.2f} cm, heading RMS {ogt['heading_rms_deg']:.3f} deg")
    pub = report.get("publish")
    if pub:
        lines.append(f"  published version {pub['version']} to {report['map']['url']} on {pub['branch']}: "
                     f"snapshot {pub['snapshot']}, tag {pub['tag']}")
    lines.append(f"  total {report['seconds_total']:.2f} s")
    return lines


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m pipeline.summary REPORT.json", file=sys.stderr)
        return 2
    print("\n".join(summarize(json.loads(Path(argv[0]).read_text()))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
