"""Benchmark: how the nightly build's cost grows with the site (the scale curve).

For each ``--areas`` side A (metres) a square A x A m floor is simulated (``mosaicmap
simulate floor --area AxA``, lawnmower, the simulator's defaults, seed 1) and built into a
fresh map repository (``mosaicmap build --map``, every stage) once per ``--workers`` count
(``[ingest]``, ``[register]`` and ``[render]`` workers set alike), each build in a fresh
child process. Printed per site and worker count: per stage wall and CPU seconds (the
build report's ``stages.<stage>.seconds`` / ``cpu_seconds``: every thread of the build),
CPU seconds per m^2, the child's peak RSS, and the bytes the build wrote (its work
directory and the map repository). Then, on the largest site, an incremental nightly
rebuild: a second day over the same world with ``--changes`` floor changes, built onto
the published map. Finally a paper projection of a ``--project`` x ``--project`` m site:
each stage's CPU seconds per m^2 on the largest site times the area, divided by N
workers at the measured speed-up of 2 workers over 1 (register and render), with the
stage that then dominates.

The simulator renders every frame (minutes for 20 x 20 m); a 40 x 40 m site took it 9
minutes on a 2-core machine on 2026-12-04 (an hour on earlier, slower hosts), its build
~26: give ``--areas`` to choose. Figures on a shared 2-core machine: wall seconds move
with the load (printed), CPU seconds less so.

    python bench/bench_scale.py [--areas 5 10 20] [--workers 1 2] [--changes 5] [--out DIR]
                                [--reuse] [--project 100] [--register-scheduler processes]
                                [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from runner import COMMAND, child, reusable, run_cli  # noqa: E402

STAGES = ("ingest", "register", "optimize", "render", "publish")


def dir_bytes(path: Path) -> int:
    """Bytes of the files below ``path`` (0 when absent)."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file()) if Path(path).exists() else 0


def simulate(out: Path, area: float, reuse: bool, *, world: Path | None = None, changes: int = 0,
             seed: int = 1) -> Path:
    """The simulated log of an ``area`` x ``area`` m floor in ``out`` (kept with ``reuse``)."""
    params = {"area": area, "seed": seed, "world": str(world) if world else None, "changes": changes}
    marker = out.with_suffix(".json")
    if reusable(marker, params, reuse) and out.exists():
        return out
    shutil.rmtree(out, ignore_errors=True)
    extra = ["--world", world, "--changes", changes] if world else []
    t0 = time.perf_counter()
    run_cli("simulate", "floor", out, "--seed", seed, "--area", f"{area:g}x{area:g}", *extra, "--quiet")
    print(f"  simulated {out.name}: {time.perf_counter() - t0:.0f} s", flush=True)
    marker.write_text(json.dumps({"params": params}))
    return out


def build(logs: Path, repo: Path, work: Path, workers: int, cfg: Path, register_scheduler: str = "threads") -> dict:
    """One nightly build in a fresh child: the report's stage seconds, the child's wall
    time, CPU time and peak RSS, and the bytes written. ``register_scheduler``: register's
    dask scheduler with more than one worker (one worker runs on a thread)."""
    text = "".join(f"[{t}]\nworkers = {workers}\n" for t in ("ingest", "register", "render"))
    if workers > 1:
        text = text.replace("[register]\n", f"[register]\nscheduler = \"{register_scheduler}\"\n")
    cfg.write_text(text)
    report = work.with_suffix(".report.json")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = (dir_bytes(work), dir_bytes(repo))
    run = child(COMMAND, "build", logs, "--map", repo, "-w", work, "--config", cfg, "--report", report, "--quiet")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    rep = json.loads(report.read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"stages": {k: rep["stages"][k] for k in STAGES if k in rep["stages"]}, "wall_s": run["wall_seconds"],
            "cpu_s": cpu, "rss_mb": run["hwm_mb"], "work_bytes": dir_bytes(work) - w0[0],
            "map_bytes": dir_bytes(repo) - w0[1], "frames": rep.get("ingest", {}).get("frames_accepted"),
            "pairs": rep.get("links", {}).get("candidates")}


def line(area: float, workers: int, b: dict) -> str:
    st = b["stages"]
    per = ", ".join(f"{k} {v['seconds']:.1f}/{v.get('cpu_seconds', 0.0):.1f}" for k, v in st.items())
    rss = ", ".join(f"{k} {v['peak_rss_mb']:.0f}" for k, v in st.items() if "peak_rss_mb" in v)
    return (f"  {area:g} x {area:g} m, {workers} worker(s): wall {b['wall_s']:.1f} s, CPU {b['cpu_s']:.1f} s "
            f"({b['cpu_s'] / area ** 2:.2f} CPU s/m^2), peak RSS {b['rss_mb']:.0f} MB, wrote "
            f"{(b['work_bytes'] + b['map_bytes']) / 1e6:.0f} MB (work {b['work_bytes'] / 1e6:.0f}, map "
            f"{b['map_bytes'] / 1e6:.0f}); stages wall/CPU s: {per}; peak RSS (MB) at each stage's end: {rss}")


def projection(largest: float, runs: dict, side: float, workers: tuple[int, ...]) -> list[str]:
    """Each stage's CPU s/m^2 on the largest site times ``side``^2, over N workers at the
    measured 2-vs-1 speed-up (stages without one: serial)."""
    one, two = runs.get(1), runs.get(2)
    base = one or two
    out = []
    for n in workers:
        total, parts = 0.0, {}
        for k, v in base["stages"].items():
            cpu_m2 = v.get("cpu_seconds", 0.0) / largest ** 2
            serial = cpu_m2 * side ** 2
            speed = 1.0
            if one and two and k in ("register", "render") and two["stages"][k]["seconds"] > 0:
                speed = one["stages"][k]["seconds"] / two["stages"][k]["seconds"]  # 2 vs 1 measured
                speed = max(1.0, speed) ** (max(n, 1).bit_length() - 1)  # the same gain per doubling
            parts[k] = serial / speed
            total += parts[k]
        top = max(parts, key=parts.get)
        out.append(f"  {side:g} x {side:g} m on {n} worker(s): ~{total / 3600:.1f} h "
                   f"({', '.join(f'{k} {v / 60:.0f} min' for k, v in parts.items())}); dominated by {top}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--areas", type=float, nargs="+", default=[5.0, 10.0, 20.0], help="site sides, metres")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to build with")
    ap.add_argument("--changes", type=int, default=5, help="floor changes of the incremental night")
    ap.add_argument("--project", type=float, default=100.0, help="side of the projected site, metres")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_scale"))
    ap.add_argument("--reuse", action="store_true", help="reuse simulated logs kept in --out")
    ap.add_argument("--register-scheduler", default="threads",
                    help="register's scheduler with more than one worker: threads or processes")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"bench_scale {datetime.now(timezone.utc).isoformat(timespec='minutes')}, {os.cpu_count()} cores, "
          f"register on {args.register_scheduler} with 2+ workers, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    res: dict = {"sites": {}}
    for area in args.areas:
        log = simulate(args.out / f"site{area:g}", area, args.reuse)
        runs = {}
        for w in args.workers:
            tag = f"site{area:g}_w{w}"
            repo, work = args.out / f"{tag}.map", args.out / f"{tag}.work"
            shutil.rmtree(repo, ignore_errors=True)
            shutil.rmtree(work, ignore_errors=True)
            runs[w] = build(log, repo, work, w, args.out / f"{tag}.toml", args.register_scheduler)
            print(line(area, w, runs[w]), flush=True)
        res["sites"][f"{area:g}"] = runs
    largest = max(args.areas)
    lw = max(args.workers)
    day2 = simulate(args.out / f"site{largest:g}_day2", largest, args.reuse, world=args.out / f"site{largest:g}",
                    changes=args.changes, seed=2)
    tag = f"site{largest:g}_w{lw}"
    inc = build(day2, args.out / f"{tag}.map", args.out / f"{tag}.day2.work", lw, args.out / f"{tag}.toml",
                args.register_scheduler)
    print(f"incremental night on {largest:g} x {largest:g} m ({args.changes} floor changes), {lw} worker(s):")
    print(line(largest, lw, inc))
    res["incremental"] = inc
    runs = {int(k): v for k, v in res["sites"][f"{largest:g}"].items()}
    print(f"projection from the {largest:g} x {largest:g} m site (CPU s/m^2 per stage x area; register and "
          "render divided by the measured 2-vs-1 speed-up per doubling of workers):")
    for s in projection(largest, runs, args.project, (1, 2, 8, 32)):
        print(s)
    print(f"load average at the end {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
