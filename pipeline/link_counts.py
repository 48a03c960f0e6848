"""The link counts of a build, in one place: ``report.json``'s ``links`` section, the printed
summary and the trajectory plot's legend all take them from :func:`link_counts`.

Pair links join two frames of the build; map links (``a = MAP_FRAME``) join a frame to the
published map and are counted apart (``map_*``). For the pair links
``rejected == rejected_registration + rejected_outliers`` and ``rejected_registration``
equals the register stage's ``registration.rejected``.
"""

from __future__ import annotations

from collections.abc import Sequence

from pipeline.anchor import MAP_FRAME
from pipeline.links import Link

__all__ = ["link_counts"]


def link_counts(links: Sequence[Link], registered: Sequence[bool]) -> dict[str, int]:
    """Counts of ``links`` after optimization (pair and map links, any order).

    ``registered[i]`` says whether link ``i`` was accepted by registration (its status before
    optimization; the optimizer only turns accepted links into rejected ones, as outliers).
    Returns ``candidates``, ``accepted``, ``rejected``, ``rejected_registration``,
    ``rejected_outliers`` (pair links) and ``map_candidates``, ``map_accepted``,
    ``map_rejected_registration``, ``map_rejected_outliers`` (map links).
    """
    if len(registered) != len(links):
        raise ValueError(f"registered: {len(registered)} flags for {len(links)} links")
    out: dict[str, int] = {}
    for prefix, is_map in (("", False), ("map_", True)):
        sel = [(lk, bool(r)) for lk, r in zip(links, registered) if (lk.a == MAP_FRAME) == is_map]
        acc = sum(lk.status == "accepted" for lk, _ in sel)
        reg_rej = sum(not r for _, r in sel)
        out[prefix + "candidates"] = len(sel)
        out[prefix + "accepted"] = acc
        if not is_map:
            out["rejected"] = len(sel) - acc
        out[prefix + "rejected_registration"] = reg_rej
        out[prefix + "rejected_outliers"] = len(sel) - acc - reg_rej
    return out
