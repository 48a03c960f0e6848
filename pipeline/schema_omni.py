"""Types and ranges of ``[omni]`` (``configs/omni.toml``) and ``[orp]`` (``configs/orp.toml``):
omni logs' floor frames and the route panorama build stage. The values and what each knob
means are in the TOML files only."""

from __future__ import annotations

from dataclasses import dataclass

from mapstore.knobs import knob

__all__ = ["OmniConfig", "OrpConfig"]

FRACTION = dict(ge=0.0, le=1.0)
NCC = dict(ge=-1.0, le=1.0)


@dataclass(frozen=True)
class OmniConfig:
    """``[omni]``: the floor annulus of an omni log's bird's-eye frames."""

    hole_margin_px: float = knob(ge=0.0)
    outer_radius_m: float = knob(gt=0.0)
    max_pixel_ratio: float = knob(ge=1.0)


@dataclass(frozen=True)
class OrpConfig:
    """``[orp]``: the route panorama build stage (registration, loop closure, merge, extension)."""

    floor_poses: bool = knob()
    default_route_id: str = knob()
    spacing_m: float = knob(gt=0.0)
    decimate_m: float = knob(ge=0.0)
    coarse_spacing_m: float = knob(gt=0.0)
    max_offset_m: float = knob(ge=0.0)
    coarse_window_m: float = knob(gt=0.0)
    highpass_cycles: int = knob(ge=0)
    coarse_min_ncc: float = knob(**NCC)
    fix_min_ncc: float = knob(**NCC)
    fix_min_valid: float = knob(**FRACTION)
    fix_gate_m: float = knob(ge=0.0)
    fix_gate_deg: float = knob(ge=0.0)
    reset_m: float = knob(ge=0.0)
    fix_sigma_m: float = knob(gt=0.0)
    fix_sigma_rad: float = knob(gt=0.0)
    robust_kernel: str = knob(choices=("cauchy", "huber", "none"), fold_case=True)
    robust_kernel_k: float = knob(gt=0.0)
    loop_max_gap_m: float = knob(ge=0.0)
    loop_window_m: float = knob(gt=0.0)
    loop_min_ncc: float = knob(**NCC)
    loop_sigma_along_m: float = knob(gt=0.0)
    loop_sigma_lateral_m: float = knob(gt=0.0)
    loop_sigma_deg: float = knob(gt=0.0)
    lateral_tolerance_m: float = knob(ge=0.0)
    merge_min_ncc: float = knob(**NCC)
    merge_max_gap_m: float = knob(ge=0.0)
    stored_weight: float = knob(ge=0.0)
    extend: bool = knob()
    extend_tolerance_m: float = knob(ge=0.0)
    extend_max_heading_deg: float = knob(ge=0.0, le=180.0)
    extend_min_m: float = knob(ge=0.0)
    extend_margin_m: float = knob(ge=0.0)
