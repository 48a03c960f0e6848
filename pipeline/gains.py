"""Per-frame exposure gains for the render's gain compensation.

Each accepted link measured the intensity ratio of its two frames over their overlap
(``Link.gain`` = mean of b / mean of a). With ``g_i`` the log-gain of frame i, every link
says ``g_b - g_a = log(gain)``; a map link (frame a is the published map, whose gain is
fixed at 1) says ``g_b = log(gain)``. A weak prior ``g_i ~ N(0, prior_sigma^2)`` fixes the
scale of frames no link reaches. The least-squares solution (a sparse, diagonally dominant
system: the graph Laplacian plus the prior) is found by preconditioned conjugate gradients.
Rendering divides each frame by ``exp(g_i)``.
"""

from __future__ import annotations

import numpy as np


def solve_log_gains(
    n: int,
    a: np.ndarray,
    b: np.ndarray,
    log_ratio: np.ndarray,
    prior_sigma: float,
    link_sigma: float = 0.01,
    *,
    tol: float = 1e-10,
    max_iter: int = 10000,
) -> np.ndarray:
    """Least-squares log-gains of ``n`` frames.

    Args:
        n: number of frames.
        a, b: (L,) frame indices of each link; ``a = -1`` for a link to the fixed map.
        log_ratio: (L,) measured ``log(mean_b / mean_a)``.
        prior_sigma: sigma (in log units) pulling each frame's log-gain to 0.
        link_sigma: sigma (log units) of one link's measured ratio.

    Returns:
        (n,) log-gains; frame i's intensity is ``exp(g_i)`` times the common exposure.
    """
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    y = np.asarray(log_ratio, dtype=float)
    ok = np.isfinite(y)
    a, b, y = a[ok], b[ok], y[ok]
    # Normal equations in units of the link weight: (L + lam I + D_map) g = rhs.
    lam = (link_sigma / prior_sigma) ** 2
    pair = a >= 0
    ap, bp, yp = a[pair], b[pair], y[pair]
    diag = np.full(n, lam)
    diag += np.bincount(ap, minlength=n) + np.bincount(bp, minlength=n)
    diag += np.bincount(b[~pair], minlength=n)
    rhs = np.bincount(bp, weights=yp, minlength=n) - np.bincount(ap, weights=yp, minlength=n)
    rhs += np.bincount(b[~pair], weights=y[~pair], minlength=n)

    def matvec(g: np.ndarray) -> np.ndarray:
        return diag * g - np.bincount(bp, weights=g[ap], minlength=n) - np.bincount(ap, weights=g[bp], minlength=n)

    g = np.zeros(n)
    r = rhs - matvec(g)
    z = r / diag
    p = z.copy()
    rz = float(r @ z)
    norm_rhs = float(np.linalg.norm(rhs)) or 1.0
    for _ in range(max_iter):
        if np.linalg.norm(r) <= tol * norm_rhs:
            break
        q = matvec(p)
        alpha = rz / float(p @ q)
        g += alpha * p
        r -= alpha * q
        z = r / diag
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return g
