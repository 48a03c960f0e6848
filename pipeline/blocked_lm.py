"""Levenberg-Marquardt over a large floor's pose graph, each step's linear system solved by blocks.

Why: GTSAM's Levenberg-Marquardt eliminates the whole graph at every step, and on a 2D floor
the elimination's fill grows as n log n: on a 40 x 40 m floor (~38,000 frames) the clique
matrices take ~320 MB beside the ~80 MB of linearized factors, the largest part of the optimize
stage's peak memory, and the one that grows faster than the floor.

How: the frames are cut into blocks of the floor (:func:`floor_blocks`: by position) and a
separator (for every factor joining two blocks, one of its ends: the frames along the blocks'
borders). Each step's damped system is then solved exactly, in three passes
(:class:`BlockSystem`):

1. each block's interior is eliminated on its own; its Bayes tree is dropped and the dense
   factor it leaves on the separator (the block's Schur complement) is kept;
2. the separator is solved from those factors and its own;
3. each block is solved again on its own, its factors on the separator taken at the
   separator's solution (their separator columns moved to the right-hand side).

Only one block's elimination lives at a time. The simulated 40 x 40 m site's optimize
(39,838 frames, 195,285 links, 2 x 2 blocks): peak 955 -> 669 MiB, CPU 1.42x (each block is
eliminated twice), every link's outlier decision and the 23 steps the same, the poses the same
to 3.4e-10 m; ``bench/bench_solver_memory.py``'s regular floor of 38,025 frames: the solve's
rise over the graph 431 -> 311 MB, CPU 5.3 -> 11.7 s (bench/README.md, 2026-12-04).

The iteration itself is GTSAM's Levenberg-Marquardt with its defaults (the isotropic damping
``lambda I``, lambda divided or multiplied by a fixed factor, a step kept when the cost falls
by more than :data:`MIN_MODEL_FIDELITY` of what the linearization predicted, the search for a
lambda given up when the cost change is below the relative tolerance, stopped on the relative
and absolute decrease of the cost): :func:`levenberg_marquardt` reaches the solution GTSAM's
optimizer reaches, to the rounding of the linear solves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_MODEL_FIDELITY", "BlockSystem", "blocks_per_side", "floor_blocks", "levenberg_marquardt"]

# GTSAM's LevenbergMarquardtParams::minModelFidelity (its default; not exposed to Python).
MIN_MODEL_FIDELITY = 1.0e-3
# A gtsam Symbol key: its character in the top 8 bits, its index below.
_INDEX_BITS = (1 << 56) - 1


def blocks_per_side(n_frames: int, block_frames: int) -> int:
    """Blocks per side of the floor for ``n_frames`` frames at ``block_frames`` frames a block
    (``floor(sqrt(n / block_frames))``); 1 (the whole graph at once) when ``block_frames`` is 0
    or the floor has fewer than 4 blocks' worth of frames."""
    if block_frames <= 0 or n_frames < 4 * block_frames:
        return 1
    return int(math.isqrt(n_frames // block_frames))


def floor_blocks(xy: np.ndarray, a: np.ndarray, b: np.ndarray, per_side: int) -> np.ndarray:
    """(N,) the block of each frame (``0 .. per_side**2 - 1``), or -1 for the separator.

    ``xy``: (N, 2) the frames' positions (metres, one frame for all); ``a``, ``b``: (F,) the two
    frames of each factor joining two frames. The floor is cut into ``per_side`` strips in x
    and in y at the positions' quantiles (as many frames in each strip). Every factor joining
    two blocks then puts one of its ends into the separator: the end with more such factors
    (a frame linked across to many, such as the published map's, is chosen once for all of
    them; ties go to the higher index). No factor joins two blocks' interiors."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    n = len(xy)
    cuts = np.linspace(0.0, 1.0, per_side + 1)[1:-1]
    bx = np.searchsorted(np.quantile(xy[:, 0], cuts), xy[:, 0], side="right") if n else np.zeros(0, int)
    by = np.searchsorted(np.quantile(xy[:, 1], cuts), xy[:, 1], side="right") if n else np.zeros(0, int)
    group = (bx * per_side + by).astype(np.int64)
    cross = group[a] != group[b]
    ca, cb = a[cross], b[cross]
    degree = np.bincount(ca, minlength=n) + np.bincount(cb, minlength=n)
    pick = np.where((degree[ca] > degree[cb]) | ((degree[ca] == degree[cb]) & (ca > cb)), ca, cb)
    group[pick] = -1
    return group


@dataclass
class BlockSystem:
    """A nonlinear factor graph split by :func:`floor_blocks`, and the exact solve of its
    damped linear systems by blocks (see the module docstring).

    ``inner``: per block the factors on its interior frames only; ``edge``: per block the
    factors joining its interior to the separator; ``border``: the factors on separator frames
    only; ``interior``: per block the keys of its frames; ``orderings``: per block its
    elimination ordering (METIS on its inner factors, nested dissection: its elimination took
    ~0.55x the time of GTSAM's own ordering for a partial elimination, constrained COLAMD, on
    the lawnmower floor); ``separator``: the separator's keys; ``dim``: the
    dimension of one pose (3 for Pose2, 4 for Similarity2); ``part_of``, ``slot``: per factor
    of the graph split, the part holding it (an index into ``inner + edge + [border]``, -1 for
    none) and its index there, for :meth:`remove`."""

    gtsam: object
    inner: list
    edge: list
    border: object
    interior: list[list[int]]
    orderings: list
    separator: list[int]
    dim: int
    part_of: np.ndarray
    slot: np.ndarray

    @classmethod
    def split(cls, gtsam, graph, xy: np.ndarray, per_side: int, dim: int) -> "BlockSystem | None":
        """``graph`` (keys: one symbol's frames ``0 .. N-1``) split into ``per_side**2``
        blocks of the floor by the frames' positions ``xy`` (N, 2); None when a factor joins
        more than two frames (the split is for pose graphs), a key is not one of the N frames'
        or the graph is empty."""
        index, factors, keys = [], [], []
        for i in range(graph.size()):
            if graph.exists(i):
                f = graph.at(i)
                ks = f.keys()
                if len(ks) > 2:
                    return None
                index.append(i)
                factors.append(f)
                keys.append(ks)
        if not factors:
            return None
        # (factors of one or two frames: every key is a factor's first or last)
        first = np.fromiter((ks[0] for ks in keys), np.uint64, len(keys))
        last = np.fromiter((ks[-1] for ks in keys), np.uint64, len(keys))
        base = int(first[0]) & ~_INDEX_BITS
        high, low = np.uint64(~_INDEX_BITS & (2**64 - 1)), np.uint64(_INDEX_BITS)
        ends = np.concatenate([first, last])
        if np.any((ends & high) != np.uint64(base)) or np.any((ends & low) >= len(xy)):
            return None  # (keys of another symbol, or past the frames given)
        first, last = (first & low).astype(np.int64), (last & low).astype(np.int64)
        pair = first != last
        group = floor_blocks(xy, first[pair], last[pair], per_side)
        keep = [g for g in range(per_side * per_side) if np.any(group == g)]
        inner = [gtsam.NonlinearFactorGraph() for _ in keep]
        edge = [gtsam.NonlinearFactorGraph() for _ in keep]
        border = gtsam.NonlinearFactorGraph()
        parts = [*inner, *edge, border]
        # each factor's part: the block of an interior end (its inner factors when every end is
        # interior, else its edge), or the border when no end is
        g1, g2 = group[first], group[last]
        mine = np.where(g1 >= 0, g1, g2)
        position = np.full(per_side * per_side, -1, np.int64)
        position[keep] = np.arange(len(keep))
        part = np.where(mine < 0, len(parts) - 1,
                        position[np.maximum(mine, 0)] + np.where((g1 >= 0) & (g2 >= 0), 0, len(keep)))
        part_of = np.full(graph.size(), -1, np.int32)
        part_of[index] = part
        slot = np.zeros(graph.size(), np.int32)
        for p in range(len(parts)):
            mine_p = np.flatnonzero(part == p)
            slot[np.asarray(index)[mine_p]] = np.arange(len(mine_p))
        for f, p in zip(factors, part.tolist()):
            parts[p].push_back(f)
        frames = np.arange(len(xy))
        interior = [(base + frames[group == g]).tolist() for g in keep]
        orderings = [_interior_ordering(gtsam, part, keys) for part, keys in zip(inner, interior)]
        return cls(gtsam, inner, edge, border, interior, orderings, (base + frames[group < 0]).tolist(), dim,
                   part_of, slot)

    @property
    def parts(self) -> list:
        """``inner + edge + [border]``: every factor graph of the split."""
        return [*self.inner, *self.edge, self.border]

    def remove(self, i: int) -> None:
        """Remove the split graph's factor ``i`` (as ``graph.remove(i)`` there)."""
        p = int(self.part_of[i])
        if p >= 0:
            self.parts[p].remove(int(self.slot[i]))
            self.part_of[i] = -1

    def error(self, values) -> float:
        """The graph's cost at ``values`` (0.5 x the sum of squared whitened errors)."""
        return float(sum(g.error(values) for g in self.parts))

    def linearize(self, values) -> tuple[list, list, object]:
        """The factors linearized at ``values``: Gaussian factor graphs as ``inner``, ``edge``
        and ``border``."""
        return ([g.linearize(values) for g in self.inner], [g.linearize(values) for g in self.edge],
                self.border.linearize(values))

    @staticmethod
    def linear_error(linear: tuple[list, list, object], delta) -> float:
        """The linearized cost (0.5 x the sum of squared whitened errors) at ``delta``."""
        inner, edge, border = linear
        return float(sum(g.error(delta) for g in (*inner, *edge, border)))

    def solve(self, linear: tuple[list, list, object], lam: float):
        """The exact solution (a VectorValues) of the linearized system ``linear`` damped by
        ``lam`` (a prior of information ``lam I`` on every pose, as GTSAM's
        Levenberg-Marquardt adds), by blocks. Raises RuntimeError where the system is
        indeterminate."""
        gtsam = self.gtsam
        inner, edge, border = linear
        eye, zero = np.eye(self.dim), np.zeros(self.dim)
        noise = gtsam.noiseModel.Isotropic.Sigma(self.dim, 1.0 / math.sqrt(lam)) if lam > 0 else None

        def damped(keys, *parts):
            out = gtsam.GaussianFactorGraph()
            for part in parts:
                out.push_back(part)
            if noise is not None:
                for k in keys:
                    out.add(k, eye, zero, noise)
            return out

        # 1. each block's interior eliminated, its Schur complement on the separator kept
        schur = []
        for keys, order, a, b in zip(self.interior, self.orderings, inner, edge):
            _, rest = damped(keys, a, b).eliminatePartialMultifrontal(order)  # (the Bayes tree goes)
            schur.append(rest)
        # 2. the separator
        sep = damped(self.separator, border, *schur)
        del schur
        delta = sep.optimize()
        del sep
        # 3. each block given the separator's solution: its edge factors with the separator's
        # columns moved to the right-hand side, then its interior solved on its own
        for keys, a, b in zip(self.interior, inner, edge):
            block = damped(keys, a, self._given(b, delta))
            delta.insert(block.optimize())  # (COLAMD here: ~0.8x the time of the METIS ordering)
        return delta

    def _given(self, edge, delta):
        """The factors of ``edge`` with their separator variables fixed at ``delta``'s values:
        ``A_i x_i + A_s x_s - b`` as ``A_i x_i - (b - A_s x_s)``."""
        gtsam = self.gtsam
        d = self.dim
        out = gtsam.GaussianFactorGraph()
        for i in range(edge.size()):
            f = edge.at(i)
            if f is None:  # (a factor removed from the graph: its slot stays, empty)
                continue
            ab = f.augmentedJacobian()  # whitened [A | b], A's columns in the keys' order
            ks = f.keys()
            rhs = ab[:, -1].copy()
            free = []
            for j, k in enumerate(ks):
                if delta.exists(k):
                    rhs -= ab[:, j * d:(j + 1) * d] @ delta.at(k)
                else:
                    free.append((k, ab[:, j * d:(j + 1) * d]))
            unit = gtsam.noiseModel.Unit.Create(len(rhs))
            if len(free) == 1:
                out.add(free[0][0], free[0][1], rhs, unit)
            else:
                out.add(free[0][0], free[0][1], free[1][0], free[1][1], rhs, unit)
        return out


def _keys_of(ordering) -> list[int]:
    """The keys of a gtsam Ordering, in order."""
    return [ordering.at(i) for i in range(ordering.size())]


def _interior_ordering(gtsam, inner, keys: list[int]):
    """An elimination ordering of a block's interior ``keys``: METIS on its inner factors
    (``inner``), then the keys no inner factor holds."""
    ordering = gtsam.Ordering()
    seen = set()
    if inner.size():
        for k in _keys_of(gtsam.Ordering.MetisNonlinearFactorGraph(inner)):
            ordering.push_back(k)
            seen.add(k)
    for k in keys:
        if k not in seen:
            ordering.push_back(k)
    return ordering


def levenberg_marquardt(system: BlockSystem, values, params) -> tuple[object, int]:
    """GTSAM's Levenberg-Marquardt (``params``: a ``gtsam.LevenbergMarquardtParams`` with
    isotropic damping and a fixed lambda factor, as its defaults) from ``values`` over
    ``system``: (the solution, the number of steps taken)."""
    if params.getDiagonalDamping() or not params.getUseFixedLambdaFactor():
        raise ValueError("the blocked Levenberg-Marquardt supports isotropic damping with a fixed lambda factor")
    gtsam = system.gtsam
    max_iterations = params.getMaxIterations()
    rel_tol, abs_tol, err_tol = params.getRelativeErrorTol(), params.getAbsoluteErrorTol(), params.getErrorTol()
    lam, factor = params.getlambdaInitial(), params.getlambdaFactor()
    upper, lower = params.getlambdaUpperBound(), params.getlambdaLowerBound()
    error = system.error(values)
    steps = 0
    if error <= err_tol:
        return values, steps
    while True:
        before = error
        linear = system.linearize(values)
        old_linear = None
        while True:  # lambdas until a step is kept, or the search is given up
            kept = give_up = False
            try:
                delta = system.solve(linear, lam)
            except RuntimeError:  # an indeterminate system: a larger lambda
                delta = None
            if delta is not None:
                if old_linear is None:
                    old_linear = system.linear_error(linear, gtsam.VectorValues.Zero(delta))
                lin_change = old_linear - system.linear_error(linear, delta)
                if lin_change >= 0:
                    new_values = values.retract(delta)
                    new_error = system.error(new_values)
                    change = error - new_error
                    if lin_change > np.finfo(float).eps * old_linear:
                        kept = change / lin_change > MIN_MODEL_FIDELITY
                    give_up = abs(change) < rel_tol * error
            if kept:
                values, error = new_values, new_error
                steps += 1
                lam = max(lower, lam / factor)
                break
            if give_up:
                break
            lam *= factor
            if lam >= upper:
                break
        del linear
        if steps >= max_iterations or not math.isfinite(before) or _converged(rel_tol, abs_tol, err_tol, before, error):
            return values, steps


def _converged(rel_tol: float, abs_tol: float, err_tol: float, before: float, after: float) -> bool:
    """GTSAM's checkConvergence: the cost below ``err_tol``, or its decrease relative to
    ``before`` at most ``rel_tol`` (when set), or absolute at most ``abs_tol``."""
    if after <= err_tol:
        return True
    decrease = before - after
    return (rel_tol > 0 and decrease / before <= rel_tol) or decrease <= abs_tol
