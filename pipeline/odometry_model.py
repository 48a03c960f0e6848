"""How far a log's prior (odometry.csv) may be trusted: one error model per log.

Kelly's (2000) dead-reckoning model: the translation error between two frames grows with the
distance travelled, ``sigma_t = error_gradient x d + sigma_floor_m``, and so does the
heading error, ``sigma_h = heading_sigma_per_m x d + heading_sigma_floor_rad``. The build's
defaults are ``[optimize] odometry_*`` (wheel odometry); a drive log may state its own in
an optional ``[odometry]`` table of drive.toml (an extension of drive log v1), because the
source of the prior is known to whoever made the log: a microscope stage does not rotate and
its position errors do not grow along the scan, GPS errors are metres whatever the
distance. ``mosaicmap import-tiles`` and ``import-geotagged`` write it.

Two kinds (``kind = "odometry"``, the default, or ``"absolute"``):

- odometry: the errors accumulate along the path as above (wheel odometry);
- absolute: every pose has its own independent error, ``sigma_m`` and ``heading_sigma_rad``
  (a stage's positioning error, a GPS fix and a compass): two poses differ by at most about
  ``sqrt(2)`` of that whatever lies between them, and the optimizer holds each pose with
  one prior of its own instead of odometry steps.

A model is a (5,) array ``[error_gradient, sigma_floor_m, heading_sigma_per_m,
heading_sigma_floor_rad, absolute]`` (dimensionless, metres, radians per metre, radians,
0/1); an absolute model is stored as the relative sigmas of two of its poses
``[0, sqrt(2) sigma_m, 0, sqrt(2) heading_sigma_rad, 1]``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.errors import BadInput

__all__ = ["FIELDS", "ABSOLUTE_FIELDS", "CONFIG_KEYS", "STAGE_MAX_HEADING_SIGMA_RAD", "is_stage", "default_model", "log_model", "absolute_sigmas",
           "parse_odometry_table", "sigmas"]

# drive.toml [odometry] keys and the [optimize] keys they override, in model order.
FIELDS = ("error_gradient", "sigma_floor_m", "heading_sigma_per_m", "heading_sigma_floor_rad")
# drive.toml [odometry] keys of kind = "absolute".
ABSOLUTE_FIELDS = ("sigma_m", "heading_sigma_rad")
KINDS = ("odometry", "absolute")
CONFIG_KEYS = ("odometry_error_gradient", "odometry_sigma_floor_m", "odometry_heading_sigma_per_m",
               "odometry_heading_sigma_floor_rad")


def default_model(cfg_opt: dict) -> np.ndarray:
    """The build's model from the ``[optimize]`` table."""
    return np.array([float(cfg_opt[k]) for k in CONFIG_KEYS] + [0.0])


def log_model(cfg_opt: dict, table: dict | None) -> np.ndarray:
    """The build's model with a log's ``[odometry]`` fields (already validated) laid over it."""
    table = table or {}
    if table.get("kind") == "absolute":
        r2 = np.sqrt(2.0)
        return np.array([0.0, r2 * float(table["sigma_m"]), 0.0, r2 * float(table["heading_sigma_rad"]), 1.0])
    m = default_model(cfg_opt)
    for i, name in enumerate(FIELDS):
        if name in table:
            m[i] = float(table[name])
    return m


def inflated_table(cfg_opt: dict, table: dict | None, translation: float, heading: float) -> dict:
    """A log's ``[odometry]`` fields with its sigmas multiplied by ``translation`` and
    ``heading`` (a prior found noisier than its model: :func:`pipeline.prior_bias.calibrate_models`)."""
    table = dict(table or {})
    if table.get("kind") == "absolute":
        table["sigma_m"] = float(table["sigma_m"]) * translation
        table["heading_sigma_rad"] = float(table["heading_sigma_rad"]) * heading
        return table
    m = log_model(cfg_opt, table)
    return {"error_gradient": m[0] * translation, "sigma_floor_m": m[1] * translation,
            "heading_sigma_per_m": m[2] * heading, "heading_sigma_floor_rad": m[3] * heading}


# An absolute model whose headings are held this well (radians, two poses' relative sigma as
# stored) is a stage: it does not rotate (import-tiles writes 0.002 per pose).
STAGE_MAX_HEADING_SIGMA_RAD = 0.01


def is_stage(model: np.ndarray) -> bool:
    """The model is a stage's: absolute, headings held to ``STAGE_MAX_HEADING_SIGMA_RAD``."""
    m = np.asarray(model, float)
    return bool(m[4] > 0.5 and m[3] <= STAGE_MAX_HEADING_SIGMA_RAD)


def absolute_sigmas(model: np.ndarray) -> tuple[float, float] | None:
    """(sigma_m, heading_sigma_rad) of one pose of an absolute model, else None."""
    m = np.asarray(model, float)
    if m[4] < 0.5:
        return None
    return float(m[1] / np.sqrt(2.0)), float(m[3] / np.sqrt(2.0))


def parse_odometry_table(path: Path, meta: dict) -> dict:
    """The optional ``[odometry]`` table of a drive.toml read from ``path``: its fields
    (numbers as non-negative, finite floats; ``kind`` "odometry" or "absolute", the latter
    with both ``sigma_m`` and ``heading_sigma_rad``, positive); {} when absent.
    :class:`BadInput` names a bad field."""
    if "odometry" not in meta:
        return {}
    table = meta["odometry"]
    if not isinstance(table, dict):
        raise BadInput(f"{path}[odometry]", "must be a table (kind, " + ", ".join(FIELDS + ABSOLUTE_FIELDS) + ")")
    kind = table.get("kind", "odometry")
    if kind not in KINDS:
        raise BadInput(f"{path}[odometry.kind]", f"must be one of {', '.join(KINDS)}, got {kind!r}")
    known = ABSOLUTE_FIELDS if kind == "absolute" else FIELDS
    out: dict = {"kind": kind} if "kind" in table else {}
    for key, v in table.items():
        if key == "kind":
            continue
        where = f"{path}[odometry.{key}]"
        if key not in known:
            raise BadInput(where, f"unknown field for kind = {kind!r} (known: " + ", ".join(known) + ")")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)) or v < 0:
            raise BadInput(where, f"must be a non-negative number, got {v!r}")
        out[key] = float(v)
    if kind == "absolute":
        for key in ABSOLUTE_FIELDS:
            if out.get(key, 0.0) <= 0:
                raise BadInput(f"{path}[odometry.{key}]", "missing or not positive (kind = \"absolute\" needs it)")
    return out


def sigmas(distance_m: np.ndarray | float, model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (metres) and heading (radians) sigmas over ``distance_m`` travelled;
    ``model`` (5,) or one per distance (..., 5). For an absolute model: those of any two of
    its poses, whatever the distance."""
    d = np.asarray(distance_m, dtype=float)
    m = np.asarray(model, dtype=float)
    return m[..., 0] * d + m[..., 1], m[..., 2] * d + m[..., 3]
