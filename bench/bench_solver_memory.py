"""Benchmark: the memory of one Levenberg-Marquardt solve of a floor's pose graph, by linear solver.

Why the 40 x 40 m build's peak is not flat in the site's size: optimize solves every frame's
pose at once, and each of GTSAM's Levenberg-Marquardt iterations eliminates the whole graph.
This bench makes the graph of a lawnmower floor without images (``--sides`` rows x columns
of Pose2 frames one metre apart, rows driven in turn; each frame linked to its row's next
two frames and to three frames of the next row: ~5 links a frame, as the simulated floors
register; a Cauchy kernel on every link, as the final solve; starting poses off by 5 cm and
0.01 rad) and solves it with each ``--solvers`` configuration, each in a fresh child
process. Printed: frames, links, the child's peak RSS after the imports, after the graph is
made and after the solve (its rise over the graph is the solve's), CPU seconds, and the
largest position error of the solution (metres; the truth is the grid).

Solvers: ``colamd`` and ``metis`` (multifrontal Cholesky, GTSAM's default, with either
ordering), ``sequential`` (sequential Cholesky), ``qr`` (multifrontal QR), ``pcg`` (GTSAM's
conjugate gradients, block-Jacobi preconditioner, 500 iterations at most), ``blocks`` (the same
Levenberg-Marquardt iteration with each linear system solved by 2 x 2 blocks of the floor:
``pipeline.blocked_lm``, what optimize does on floors of 4 x ``[optimize] block_frames``
frames and more).

    python bench/bench_solver_memory.py [--sides 50 100 195] [--solvers colamd metis sequential pcg blocks]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peak_memory import hwm_kb  # noqa: E402


def _grid_graph(gtsam, side: int):
    """(graph, initial values, (N, 2) true positions) of a ``side`` x ``side`` lawnmower floor."""
    import numpy as np

    X = gtsam.symbol_shorthand.X
    order = np.arange(side * side).reshape(side, side)
    order[1::2] = order[1::2, ::-1]  # (every other row driven back)
    truth = np.zeros((side * side, 2))
    truth[order.ravel(), 0] = np.tile(np.arange(side), side)
    truth[order.ravel(), 1] = np.repeat(np.arange(side), side)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*truth[0], 0.0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    cov = np.diag([1e-4, 1e-4, 1e-6])
    kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(3.0)
    links = 0
    for r in range(side):
        for c in range(side):
            for dr, dc in ((0, 1), (0, 2), (1, -1), (1, 0), (1, 1)):
                if 0 <= r + dr < side and 0 <= c + dc < side:
                    i, j = int(order[r, c]), int(order[r + dr, c + dc])
                    d = truth[j] - truth[i]
                    noise = gtsam.noiseModel.Robust.Create(kernel, gtsam.noiseModel.Gaussian.Covariance(cov))
                    graph.add(gtsam.BetweenFactorPose2(X(i), X(j), gtsam.Pose2(d[0], d[1], 0.0), noise))
                    links += 1
    rng = np.random.default_rng(0)
    values = gtsam.Values()
    for i, (x, y) in enumerate(truth):
        values.insert(X(i), gtsam.Pose2(x + rng.normal(0, 0.05), y + rng.normal(0, 0.05), rng.normal(0, 0.01)))
    return graph, values, truth, links


def _params(gtsam, solver: str):
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(20)
    if solver in ("colamd", "metis", "blocks"):
        p.setOrderingType("METIS" if solver == "metis" else "COLAMD")
    elif solver == "sequential":
        p.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    elif solver == "qr":
        p.setLinearSolverType("MULTIFRONTAL_QR")
    elif solver == "pcg":
        p.setLinearSolverType("ITERATIVE")
        pcg = gtsam.PCGSolverParameters()
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        pcg.maxIterations, pcg.epsilon_rel, pcg.epsilon_abs = 500, 1e-6, 1e-9
        p.setIterativeParams(pcg)
    else:
        raise SystemExit(f"unknown solver {solver!r}")
    return p


def one(solver: str, side: int) -> dict:
    """One solve in this process (the child's part)."""
    import gtsam
    import numpy as np

    imports = hwm_kb() / 1e3
    graph, values, truth, links = _grid_graph(gtsam, side)
    made = hwm_kb() / 1e3
    cpu = time.process_time()
    if solver == "blocks":  # the same iteration, its linear systems solved by 2 x 2 blocks of the floor
        from pipeline.blocked_lm import BlockSystem, levenberg_marquardt

        system = BlockSystem.split(gtsam, graph, gtsam.utilities.extractPose2(values)[:, :2], 2, 3)
        out = levenberg_marquardt(system, values, _params(gtsam, solver))[0]
    else:
        out = gtsam.LevenbergMarquardtOptimizer(graph, values, _params(gtsam, solver)).optimize()
    cpu = time.process_time() - cpu
    peak = hwm_kb() / 1e3
    est = gtsam.utilities.extractPose2(out)[:, :2]
    return {"solver": solver, "frames": side * side, "links": links, "imports_mb": imports, "graph_mb": made,
            "peak_mb": peak, "cpu_s": cpu, "max_error_m": float(np.abs(est - truth).max())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sides", type=int, nargs="+", default=[50, 100, 195], help="frames per row (= rows)")
    ap.add_argument("--solvers", nargs="+", default=["colamd", "metis", "sequential", "pcg", "blocks"])
    ap.add_argument("--one", nargs=2, metavar=("SOLVER", "SIDE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]))))
        return 0
    print(f"bench_solver_memory {datetime.now(timezone.utc).isoformat(timespec='minutes')}, each solve in a fresh "
          "child process")
    for side in args.sides:
        for solver in args.solvers:
            run = subprocess.run([sys.executable, __file__, "--one", solver, str(side)], capture_output=True, text=True)
            if run.returncode != 0:
                print(f"  {side} x {side}, {solver}: failed: {(run.stderr.strip().splitlines() or ['?'])[-1]}")
                continue
            r = json.loads(run.stdout.strip().splitlines()[-1])
            print(f"  {r['frames']:6d} frames, {r['links']:6d} links, {solver:10s}: RSS imports {r['imports_mb']:.0f} MB, "
                  f"graph {r['graph_mb']:.0f} MB, solve peak {r['peak_mb']:.0f} MB (+{r['peak_mb'] - r['graph_mb']:.0f}"
                  f" MB, {1e3 * (r['peak_mb'] - r['graph_mb']) / r['frames']:.1f} KB a frame), CPU {r['cpu_s']:.1f} s, "
                  f"largest error {r['max_error_m']:.1e} m", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
