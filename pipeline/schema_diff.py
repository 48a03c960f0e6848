"""Types and ranges of the tables of ``configs/diff.toml`` (`mosaicmap diff`).

One frozen dataclass per table; the values (and what each knob means) are in the TOML file
only. ``[diff.routes]`` is :class:`mapstore.diff.RouteDiffParams` itself (mapstore reads it).
"""

from __future__ import annotations

from dataclasses import dataclass

from mapstore.knobs import knob

__all__ = ["DiffConfig", "DiffImpactConfig", "DiffTruthConfig", "DiffReportConfig"]

FRACTION = dict(ge=0.0, le=1.0)


@dataclass(frozen=True)
class DiffConfig:
    """``[diff]``: what is compared, illumination, misalignment, thresholds, work."""

    valid_erode_px: int = knob(ge=0)
    blur_sigma_px: float = knob(ge=0.0)
    gain_block_px: int = knob(ge=1)
    gain_window_px: int = knob(ge=1)
    gain_min_valid_fraction: float = knob(gt=0.0, le=1.0)
    gain_smooth_blocks: float = knob(ge=0.0)
    max_shift_px: float = knob(**FRACTION)
    threshold_sigma: float = knob(ge=0.0)
    noise_block_quantile: float = knob(**FRACTION)
    max_noise: float = knob(ge=0.0)
    min_contrast: float = knob(ge=0.0)
    mean_window_px: int = knob(ge=0)
    close_px: int = knob(ge=0)
    edge_band_px: int = knob(ge=0)
    max_hole_m2: float = knob(ge=0.0)
    edge_ring_px: int = knob(ge=1)
    min_edge_step: float = knob(ge=0.0)
    part_min_edge_step: float = knob(ge=0.0)
    rethreshold_factor: float = knob(ge=1.0)
    rethreshold_steps: int = knob(ge=0)
    min_region_area_m2: float = knob(ge=0.0)
    observed_close_px: int = knob(ge=0)
    window_core_px: int = knob(ge=1)
    polygon_tolerance_px: float = knob(ge=0.0)


@dataclass(frozen=True)
class DiffImpactConfig:
    """``[diff.impact]``: localization impact of a changed region."""

    texture_min: float = knob(ge=0.0)
    uniqueness_min: float = knob(ge=0.0, le=2.0)  # C1 - C2
    min_cell_fraction: float = knob(**FRACTION)


@dataclass(frozen=True)
class DiffTruthConfig:
    """``[diff.truth]``: scoring against a ground-truth change mask (``--truth``)."""

    min_observed_fraction: float = knob(**FRACTION)
    min_recall: float = knob(**FRACTION)


@dataclass(frozen=True)
class DiffReportConfig:
    """``[diff.report]``: the images of the HTML report."""

    crop_max_px: int = knob(ge=1)
    margin_px: int = knob(ge=0)
    max_crops: int = knob(ge=0)
    overview_max_px: int = knob(ge=1)
    route_figure_rows: int = knob(ge=1)
    route_figure_scale: int = knob(ge=1)
    max_route_figures: int = knob(ge=0)
