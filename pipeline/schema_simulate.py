"""Types and ranges of the tables of ``configs/simulate.toml`` (`mosaicmap simulate ...`).

One frozen dataclass per table; the values (and what each knob means) are in the TOML file
only. The floor and omni simulators share the route, odometry and sensor tables' shapes.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapstore.knobs import knob

__all__ = ["SimulateConfig", "SimFloorConfig", "SimFloorCameraConfig", "SimFloorMotionConfig", "SimFloorRoutesConfig",
           "SimOdometryConfig", "SimSensorConfig", "SimTexturesConfig", "SimChangeKindsConfig", "SimTilesConfig",
           "SimOmniConfig", "SimOmniCameraConfig", "SimOmniMotionConfig", "SimOmniRoutesConfig", "SimOmniWorldConfig"]

FRACTION = dict(ge=0.0, le=1.0)
ROUTES = ("lawnmower", "loop", "figure8", "random")
GREY = dict(ge=0.0, le=255.0)
#: libpng row filters (OpenImageIO "png:filter": 0 = adaptive, or a sum of 8, 16, 32, 64, 128).
PNG_FILTER = dict(ge=0, le=248)
#: A positive [low, high] range.
POS_RANGE = dict(gt=0.0, ordered=True)


@dataclass(frozen=True)
class SimulateConfig:
    """``[simulate]``: seed and threads of every simulator."""

    seed: int = knob(ge=0)
    workers: int = knob(ge=0)  # 0 = one per core


@dataclass(frozen=True)
class SimFloorConfig:
    """``[simulate.floor]``: the downward-camera floor simulator."""

    area_m: tuple[float, float] = knob(gt=0.0)
    pixel_size_m: float = knob(gt=0.0)
    route: str = knob(choices=ROUTES)
    texture: str = knob()  # "procedural" or a photograph's path
    changes: int = knob(ge=0)
    illumination: float = knob(gt=0.0)
    height_jitter: float = knob(ge=0.0, lt=1.0)  # 0 = off
    height_jitter_wavelength_m: float = knob(gt=0.0)
    image_bits: int = knob(choices=(8, 16))
    png_compression: int = knob(ge=0, le=9)
    png_filter: int = knob(**PNG_FILTER)
    world_margin_m: float = knob(ge=0.0)


@dataclass(frozen=True)
class SimFloorCameraConfig:
    """``[simulate.floor.camera]``: the downward pinhole camera."""

    frame_size: tuple[int, int] = knob(ge=1)
    height_m: float = knob(gt=0.0)
    principal_offset_px: tuple[float, float] = knob()
    k1: float = knob()
    k2: float = knob()
    p1: float = knob()
    p2: float = knob()
    vignetting: tuple[float, float] = knob()
    declare_vignetting: bool = knob()


@dataclass(frozen=True)
class SimFloorMotionConfig:
    """``[simulate.floor.motion]``: speed, frame spacing and motion blur."""

    speed_m_s: float = knob(gt=0.0)
    frame_spacing_m: float = knob(gt=0.0)
    start_time_s: float = knob(ge=0.0)
    exposure_s: float = knob(ge=0.0)
    blur_step_px: float = knob(gt=0.0)


@dataclass(frozen=True)
class SimFloorRoutesConfig:
    """``[simulate.floor.routes]``: route shapes over the area."""

    inset_m: float = knob(ge=0.0)
    lane_overlap: float = knob(ge=0.0, lt=1.0)
    laps: int = knob(ge=1)
    loop_corner_radius_m: float = knob(ge=0.0)
    random_length_m: float = knob(gt=0.0)
    random_turn_radius_m: float = knob(gt=0.0)
    random_waypoint_reach_m: float = knob(gt=0.0)
    random_walk_step_m: float = knob(gt=0.0)
    dense_step_m: float = knob(gt=0.0)


@dataclass(frozen=True)
class SimOdometryConfig:
    """``[simulate.floor.odometry]``, ``[simulate.omni.odometry]``: the odometry's errors."""

    drift: float = knob(ge=0.0)  # 0 = perfect odometry
    rate_hz: float = knob(gt=0.0)
    frame: str = knob(choices=("world", "origin"))
    scale_share: float = knob(ge=0.0)
    heading_walk_share: float = knob(ge=0.0)
    reference_distance_m: float = knob(gt=0.0)
    heading_noise_rad: float = knob(ge=0.0)
    distance_noise: float = knob(ge=0.0)


@dataclass(frozen=True)
class SimSensorConfig:
    """``[simulate.floor.sensor]``, ``[simulate.omni.sensor]``: noise and exposure drift."""

    noise_sigma: float = knob(ge=0.0)
    exposure_drift: float = knob(ge=0.0, lt=1.0)
    exposure_drift_components: int = knob(ge=0)
    exposure_drift_period_s: tuple[float, float] = knob(**POS_RANGE)


@dataclass(frozen=True)
class SimTexturesConfig:
    """``[simulate.floor.textures]``: the procedural worn-concrete texture."""

    mean: float = knob(**GREY)
    std: float = knob(ge=0.0)
    clip_low: float = knob(**GREY)
    clip_high: float = knob(**GREY)
    band_limit_sigma_px: float = knob(ge=0.0)
    grain_scales_m: tuple[float, ...] = knob(gt=0.0)
    grain_weights: tuple[float, ...] = knob(ge=0.0)
    scratch_density_per_m2: float = knob(ge=0.0)
    scratch_length_m: tuple[float, float] = knob(**POS_RANGE)
    scratch_width_px: int = knob(ge=1)
    scratch_contrast: tuple[float, float] = knob(ge=0.0, ordered=True)
    crack_density_per_m2: float = knob(ge=0.0)
    crack_length_m: tuple[float, float] = knob(**POS_RANGE)
    crack_step_m: float = knob(gt=0.0)
    crack_turn_rad: float = knob(ge=0.0)
    crack_width_px: int = knob(ge=1)
    crack_contrast: tuple[float, float] = knob(ge=0.0, ordered=True)
    spot_density_per_m2: float = knob(ge=0.0)
    spot_radius_m: tuple[float, float] = knob(**POS_RANGE)
    spot_contrast: tuple[float, float] = knob(ge=0.0, ordered=True)
    low_texture_density_per_m2: float = knob(ge=0.0)
    directional_density_per_m2: float = knob(ge=0.0)
    min_patches: int = knob(ge=0)
    patch_size_m: tuple[float, float] = knob(**POS_RANGE)
    low_texture_sigma_m: float = knob(gt=0.0)
    low_texture_amplitude: float = knob(ge=0.0)
    directional_scale_m: float = knob(gt=0.0)
    patch_edge_m: float = knob(ge=0.0)
    photo_width_m: float = knob(ge=0.0)  # 0 = the texture pixel size


@dataclass(frozen=True)
class SimChangeKindsConfig:
    """``[simulate.floor.change_kinds]``: the changes made to a world between days."""

    weights: tuple[float, float, float] = knob(ge=0.0)
    stain_size_m: tuple[float, float] = knob(**POS_RANGE)
    stain_contrast: tuple[float, float] = knob(ge=0.0, ordered=True)
    repaint_area_m2: tuple[float, float] = knob(**POS_RANGE)
    repaint_mean: tuple[float, float] = knob(**GREY, ordered=True)
    repaint_std: float = knob(ge=0.0)
    marking_length_m: tuple[float, float] = knob(**POS_RANGE)
    marking_width_m: tuple[float, float] = knob(**POS_RANGE)
    marking_level: tuple[float, float] = knob(**GREY, ordered=True)
    edge_m: float = knob(ge=0.0)
    mask_weight: float = knob(gt=0.0, le=1.0)


@dataclass(frozen=True)
class SimTilesConfig:
    """``[simulate.tiles]``: the stage-scanned microscope tile grid."""

    grid: tuple[int, int] = knob(ge=1)
    tile_size: tuple[int, int] = knob(ge=1)
    overlap: float = knob(ge=0.0, lt=1.0)
    stage_error_px: float = knob(ge=0.0)
    order: str = knob(choices=("row", "snake"))
    noise_sigma: float = knob(ge=0.0)
    gain: float = knob(ge=0.0, lt=1.0)
    bits: int = knob(choices=(8, 16))
    value_range: tuple[int, ...] = knob(ge=0, le=65535, lengths=(0, 2), ordered=True)  # [] = full range
    blank_tiles: tuple[int, ...] = knob(ge=0)
    blank_count: int = knob(ge=0)
    blank_level: float = knob(**GREY)
    hot_pixels: int = knob(ge=0)
    texture_pixel_size_m: float = knob(gt=0.0)
    compression: str = knob(choices=("none", "zip", "lzw"))


@dataclass(frozen=True)
class SimOmniConfig:
    """``[simulate.omni]``: the omnidirectional simulator's room, route and options."""

    room_m: tuple[float, float] = knob(gt=0.0)
    wall_height_m: float = knob(gt=0.0)
    route: str = knob(choices=ROUTES)
    night: bool = knob()
    height_offset_m: float = knob()
    move_objects: float = knob(ge=0.0)  # 0 = none
    offset_m: float = knob()
    angle_deg: float = knob(gt=-90.0, lt=90.0)
    across_amplitude_m: float = knob(ge=0.0)
    png_compression: int = knob(ge=0, le=9)
    png_filter: int = knob(**PNG_FILTER)


@dataclass(frozen=True)
class SimOmniCameraConfig:
    """``[simulate.omni.camera]``: the hyperboloidal-mirror camera."""

    frame_size: tuple[int, int] = knob(ge=1)
    a_m: float = knob(gt=0.0)
    b_m: float = knob(gt=0.0)
    height_m: float = knob(gt=0.0)
    rim_radius_frac: float = knob(gt=0.0, le=1.0)
    rim_elevation_deg: float = knob(gt=-90.0, lt=90.0)
    hole_radius_frac: float = knob(ge=0.0, lt=1.0)
    principal_offset_px: tuple[float, float] = knob()
    vignetting: tuple[float, float] = knob()
    declare_vignetting: bool = knob()
    outside_level: float = knob(**GREY)
    hole_level: float = knob(**GREY)


@dataclass(frozen=True)
class SimOmniMotionConfig:
    """``[simulate.omni.motion]``: speed, frame spacing, first frame time."""

    speed_m_s: float = knob(gt=0.0)
    frame_spacing_m: float = knob(gt=0.0)
    start_time_s: float = knob(ge=0.0)


@dataclass(frozen=True)
class SimOmniRoutesConfig(SimFloorRoutesConfig):
    """``[simulate.omni.routes]``: the floor's route knobs plus the lawnmower lane spacing."""

    lane_spacing_m: float = knob(gt=0.0)


@dataclass(frozen=True)
class SimOmniWorldConfig:
    """``[simulate.omni.world]``: the room's surfaces, objects and lighting."""

    texel_m: float = knob(gt=0.0)
    mip_levels: int = knob(ge=1)
    panel_width_m: tuple[float, float] = knob(**POS_RANGE)
    panel_level: tuple[float, float] = knob(**GREY, ordered=True)
    mottle_scale_m: float = knob(gt=0.0)
    mottle_amplitude: float = knob(ge=0.0)
    baseboard_m: float = knob(ge=0.0)
    baseboard_level: float = knob(**GREY)
    doors: int = knob(ge=0)
    door_size_m: tuple[float, float] = knob(gt=0.0)
    door_level: float = knob(**GREY)
    posters: int = knob(ge=0)
    poster_width_m: tuple[float, float] = knob(**POS_RANGE)
    poster_height_m: tuple[float, float] = knob(**POS_RANGE)
    poster_bottom_m: tuple[float, float] = knob(ge=0.0, ordered=True)
    poster_scale_m: float = knob(gt=0.0)
    poster_contrast: float = knob(ge=0.0)
    windows: int = knob(ge=0)
    window_width_m: float = knob(gt=0.0)
    window_z_m: tuple[float, float] = knob(ge=0.0, ordered=True)
    window_day_level: float = knob(**GREY)
    window_night_level: float = knob(**GREY)
    objects: int = knob(ge=0)
    object_size_m: tuple[float, float] = knob(**POS_RANGE)
    object_height_m: tuple[float, float] = knob(**POS_RANGE)
    object_route_clearance_m: float = knob(ge=0.0)
    object_gap_m: float = knob(ge=0.0)
    ceiling_level: float = knob(**GREY)
    lamps: tuple[int, int] = knob(ge=0)
    lamp_size_m: tuple[float, float] = knob(gt=0.0)
    lamp_level: float = knob(**GREY)
    day_ambient: float = knob(ge=0.0)
    day_window_gain: float = knob(ge=0.0)
    day_falloff_m: float = knob(gt=0.0)
    night_ambient: float = knob(ge=0.0)
    night_lamp_gain: float = knob(ge=0.0)
    night_lamp_sigma_m: float = knob(gt=0.0)
