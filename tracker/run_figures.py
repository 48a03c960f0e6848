"""The figures of a tracking run that do not depend on what was tracked (floor or route).

Both sessions (:mod:`tracker.session`, :mod:`tracker.orp_session`) report them under the same
keys; each step of either carries ``ok``, ``status``, ``mode``, ``fix_seconds``,
``fix_cpu_seconds``, ``reloc_seconds``, ``seconds`` and ``index``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = ["run_figures"]


def _pct(a: np.ndarray, q: float) -> float | None:
    return float(np.percentile(a, q)) if len(a) else None


def _ms(s: float | None) -> float | None:
    return None if s is None else s * 1000.0


def run_figures(steps: Sequence, modes: Sequence[str], reloc_mode: str) -> dict:
    """Counts and timings of ``steps``: ``fixes`` (frames), ``ok``, ``ok_rate``, ``statuses``
    and ``modes`` (counts; every name of ``modes`` present), ``fixes_per_s`` and
    ``latency_ms`` (fixes from the prediction, wall clock: p50, p99, max; milliseconds),
    ``cpu_fixes_per_s`` and ``cpu_latency_ms`` (the same in the tracker thread's CPU time),
    ``relocalizations`` (steps whose mode is ``reloc_mode``), ``relocalization`` (attempts,
    ``seconds_median``, ``seconds_max``, ``first_ok_frame``: the first step relocalized),
    ``tracker_seconds`` (all steps)."""
    n = len(steps)
    ok = np.array([st.ok for st in steps], bool)
    statuses: dict[str, int] = {}
    counts: dict[str, int] = {m: 0 for m in modes}
    for st in steps:
        statuses[st.status] = statuses.get(st.status, 0) + 1
        counts[st.mode] += 1
    fix_t = np.array([st.fix_seconds for st in steps if st.fix_seconds > 0])
    cpu_t = np.array([st.fix_cpu_seconds for st in steps if st.fix_seconds > 0])
    rel_t = np.array([st.reloc_seconds for st in steps if st.reloc_seconds > 0])
    first = next((st.index for st in steps if st.mode == reloc_mode), None)
    return {
        "fixes": n,
        "ok": int(ok.sum()),
        "ok_rate": float(ok.mean()) if n else 0.0,
        "statuses": statuses,
        "modes": counts,
        "fixes_per_s": float(len(fix_t) / fix_t.sum()) if len(fix_t) else None,
        "latency_ms": {"p50": _ms(_pct(fix_t, 50)), "p99": _ms(_pct(fix_t, 99)),
                       "max": _ms(float(fix_t.max()) if len(fix_t) else None)},
        "cpu_fixes_per_s": float(len(cpu_t) / cpu_t.sum()) if len(cpu_t) and cpu_t.sum() > 0 else None,
        "cpu_latency_ms": {"p50": _ms(_pct(cpu_t, 50)), "p99": _ms(_pct(cpu_t, 99))},
        "relocalizations": counts[reloc_mode],
        "relocalization": {"attempts": len(rel_t), "seconds_median": _pct(rel_t, 50),
                           "seconds_max": float(rel_t.max()) if len(rel_t) else None, "first_ok_frame": first},
        "tracker_seconds": float(sum(st.seconds for st in steps)),
    }
