"""Types and ranges of the tables of ``configs/floor.toml`` (the floor map pipeline).

One frozen dataclass per table; the values (and what each knob means) are in the TOML file
only. Bounds follow how each knob is used: a 0 documented as "off", "all" or "automatic"
stays allowed.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapstore.knobs import knob

__all__ = ["MapConfig", "RenderConfig", "PublishConfig", "IngestConfig", "FlatFieldConfig", "GroundPlaneConfig",
           "PhotometryConfig", "QualityConfig", "BuildConfig", "OptimizeConfig", "RegisterConfig", "SCHEDULER", "SCHEDULER_URLS",
           "INTERPOLATION"]

#: ``scheduler`` knobs: a local dask scheduler, or a dask.distributed one's address.
SCHEDULER = ("threads", "processes", "sync")
SCHEDULER_URLS = ("tcp", "tls", "inproc", "ucx", "ws", "wss")  # dask.distributed comm schemes
#: OpenCV interpolations named in the configuration (pipeline/mosaic.py, pipeline/camera.py).
INTERPOLATION = ("cubic", "linear", "lanczos4")
#: A fraction of something (0..1).
FRACTION = dict(ge=0.0, le=1.0)
#: A percentile (0..100).
PERCENTILE = dict(ge=0.0, le=100.0)
#: An NCC threshold (-1..1).
NCC = dict(ge=-1.0, le=1.0)


@dataclass(frozen=True)
class MapConfig:
    """``[map]``: pixel size, storage layout and extent of the map grid."""

    pixel_size_m: float = knob(ge=0.0)  # 0 = automatic
    chunk_px: int = knob(ge=1)
    shard_px: int = knob(ge=1)
    zstd_level: int = knob(ge=1, le=22)
    site_extent_m: tuple[float, ...] = knob(lengths=(0, 4))
    margin_m: float = knob(ge=0.0)
    layer_cell_px: int = knob(ge=1)


@dataclass(frozen=True)
class RenderConfig:
    """``[render]``: frame selection, blending, layers and the render's parallelism."""

    interpolation: str = knob(choices=INTERPOLATION)
    composite: str = knob(choices=("seams", "blend"))
    seam_frames: int = knob(ge=1)
    frame_step_fraction: float = knob(ge=0.0)  # 0 = all frames
    frame_turn_rad: float = knob(ge=0.0)
    coverage_depth: int = knob(ge=0)  # 0 = every frame kept
    select_cell_px: int = knob(ge=1)
    feather_px: float = knob(ge=0.0)  # 0 = hard edges
    gain_compensation: bool = knob()
    gain_prior_sigma: float = knob(gt=0.0)
    gain_link_sigma: float = knob(gt=0.0)
    uniqueness_template_px: int = knob(ge=1)
    uniqueness_search_radius_px: int = knob(ge=1)
    uniqueness_exclusion_px: int = knob(ge=0)
    uniqueness_level: int = knob(ge=0, le=1)  # 0 = level 0, 1 = the 2x-reduced mosaic
    uniqueness_recheck: tuple[float, ...] = knob(lengths=(0, 2), ordered=True)  # [] = none
    texture_window_px: int = knob(ge=1)
    texture_sigma_px: float = knob(ge=0.0)  # 0 = no smoothing
    texture_sample_px: int = knob(ge=1)
    task_block_shards: int = knob(ge=1)
    workers: int = knob(ge=0)  # 0 = one per core
    scheduler: str = knob(choices=SCHEDULER + ("auto",), url_schemes=SCHEDULER_URLS)
    processes_min_mpix: float = knob(ge=0.0)
    frame_cache_mb: float = knob(ge=0.0)


@dataclass(frozen=True)
class PublishConfig:
    """``[publish]``: branch, tag format and the quality gates of a build."""

    branch: str = knob()
    tag_format: str = knob()
    min_accepted_fraction: float = knob(**FRACTION)
    max_unlinked_fraction: float = knob(**FRACTION)
    max_unverified_overlap_fraction: float = knob(**FRACTION)
    max_residual_rms_px: float = knob(ge=0.0)
    max_residual_px: float = knob(ge=0.0)
    min_anchored_fraction: float = knob(**FRACTION)
    max_extent_growth_fraction: float = knob(ge=0.0)
    max_extent_growth_frames: float = knob(ge=0.0)


@dataclass(frozen=True)
class IngestConfig:
    """``[ingest]``: bad images, rectification and the caps on what is read."""

    on_bad_image: str = knob(choices=("skip", "fail"))
    max_bad_fraction: float = knob(**FRACTION)
    interpolation: str = knob(choices=INTERPOLATION)
    valid_mask_erode_px: int = knob(ge=0)
    odometry_time_tolerance_s: float = knob(ge=0.0)
    max_rectified_pixels: int = knob(ge=1)
    max_image_pixels: int = knob(ge=1)
    max_image_bytes: int = knob(ge=1)
    follow_symlinks: bool = knob()
    workers: int = knob(ge=0)  # 0 = one per core


@dataclass(frozen=True)
class FlatFieldConfig:
    """``[ingest.flatfield]``: vignetting correction."""

    mode: str = knob(choices=("auto", "calibration", "none"))
    sample_frames: int = knob(ge=1)
    min_frames: int = knob(ge=1)


@dataclass(frozen=True)
class GroundPlaneConfig:
    """``[ingest.ground_plane]``: aerial frames' tilt and height measured from the images."""

    mode: str = knob(choices=("auto", "images", "none"))
    max_side_px: int = knob(ge=64)
    features: int = knob(ge=100)
    pair_span: int = knob(ge=1)
    neighbours: int = knob(ge=0)  # 0 = only the next frames
    neighbour_distance: float = knob(ge=0.0)
    ratio: float = knob(gt=0.0, le=1.0)
    ransac_px: float = knob(gt=0.0)
    min_inliers: int = knob(ge=8)
    agree_rad: float = knob(gt=0.0)
    max_tilt_rad: float = knob(gt=0.0, lt=1.5)
    height_sigma: float = knob(gt=0.0)
    scale_sigma_floor: float = knob(gt=0.0)
    height_scale: str = knob(choices=("auto", "positions", "records"))
    min_step_fraction: float = knob(ge=0.0)


@dataclass(frozen=True)
class PhotometryConfig:
    """``[ingest.photometry]``: per-log intensity normalization."""

    normalize: str = knob(choices=("auto", "always", "none"))
    auto_max_used_fraction: float = knob(**FRACTION)
    low_percentile: float = knob(**PERCENTILE)
    high_percentile: float = knob(**PERCENTILE)
    target_levels: tuple[float, float] = knob(ge=0.0, le=255.0, ordered=True)
    sample_frames: int = knob(ge=1)


@dataclass(frozen=True)
class QualityConfig:
    """``[ingest.quality]``: per-frame hot pixel, texture, isotropy and exposure checks."""

    hot_pixel_sigmas: float = knob(ge=0.0)  # 0 = off
    texture_window_px: int = knob(ge=1)
    texture_smoothing_sigma_px: float = knob(ge=0.0)  # 0 = no smoothing
    min_local_texture: float = knob(ge=0.0)
    noise_texture_factor: float = knob(ge=0.0)
    min_textured_fraction: float = knob(**FRACTION)
    min_isotropy: float = knob(**FRACTION)
    isotropy_min_textured_fraction: float = knob(**FRACTION)
    isotropy_block_px: int = knob(ge=1)
    isotropy_sharp_block: float = knob(**FRACTION)
    blur_max_sharp_fraction: float = knob(**FRACTION)
    clip_margin_codes: float = knob(ge=0.0)
    pileup_min_fraction: float = knob(**FRACTION)
    max_saturated_fraction: float = knob(**FRACTION)
    max_dark_fraction: float = knob(**FRACTION)
    warn_fraction: float = knob(**FRACTION)


@dataclass(frozen=True)
class BuildConfig:
    """``[build]``: the stages `mosaicmap build` runs."""

    stages: tuple[str, ...] = knob(choices=("ingest", "register", "optimize", "orp", "render", "publish"))


@dataclass(frozen=True)
class OptimizeConfig:
    """``[optimize]``: the pose graph (GTSAM): noise models, gates, robust kernel, solver."""

    pose_model: str = knob(choices=("pose2", "similarity2"), fold_case=True)
    scale_sigma_per_frame: float = knob(gt=0.0)
    scale_prior_sigma: float = knob(gt=0.0)
    odometry_error_gradient: float = knob(ge=0.0)
    odometry_heading_sigma_per_m: float = knob(ge=0.0)
    odometry_sigma_floor_m: float = knob(gt=0.0)
    odometry_heading_sigma_floor_rad: float = knob(gt=0.0)
    unverified_overlap_min: float = knob(**FRACTION)  # [publish] max_unverified_overlap_fraction counts these
    jump_speed_factor: float = knob(ge=0.0)  # 0 = off
    jump_speed_percentile: float = knob(**PERCENTILE)
    jump_slack_frames: float = knob(ge=0.0)
    jump_max_frames: int = knob(ge=0)
    anchor_sigma_m: float = knob(gt=0.0)
    anchor_sigma_rad: float = knob(gt=0.0)
    log_start_sigma_m: float = knob(gt=0.0)
    log_start_sigma_rad: float = knob(gt=0.0)
    odometry_gate_sigmas: float = knob(ge=0.0)  # 0 = off
    calibrate_link_covariance: bool = knob()
    calibration_tolerance: float = knob(ge=1.0)  # a factor either way
    calibration_min_loops: int = knob(ge=0)
    robust_kernel: str = knob(choices=("cauchy", "huber", "none"), fold_case=True)
    robust_kernel_k: float = knob(gt=0.0)
    outlier_chi2: float = knob(gt=0.0)
    outlier_max_residual_px: float = knob(ge=0.0)  # 0 = off
    max_outlier_passes: int = knob(ge=0)
    resolve_max_iterations: int = knob(ge=1)
    marginals_max_frames: int = knob(ge=0)
    robust_anneal_k: tuple[float, ...] = knob(gt=0.0, decreasing=True)
    anneal_skip_ratio: float = knob(gt=0.0)
    outlier_policy: str = knob(choices=("worst_per_cluster", "all"))
    outlier_cluster_frames: int = knob(ge=0)
    max_iterations: int = knob(ge=1)
    relative_error_tol: float = knob(ge=0.0)
    absolute_error_tol: float = knob(ge=0.0)
    ordering: str = knob(choices=("COLAMD", "METIS"), fold_case=True)
    block_frames: int = knob(ge=0)  # 0 = off
    stage_relative_error_tol: float = knob(ge=0.0)


@dataclass(frozen=True)
class RegisterConfig:
    """``[register]``: candidate pairs, prior correction, revisits and pairwise registration."""

    sequential_window: int = knob(ge=1)
    min_predicted_overlap: float = knob(**FRACTION)
    revisit_relative_overlap: float = knob(**FRACTION)
    revisit_min_path_m: float = knob(ge=0.0)
    revisit_min_path_frames: float = knob(ge=0.0)
    max_revisits_per_frame: int = knob(ge=0)
    chain_gate_sigmas: float = knob(gt=0.0)
    prior_correction: bool = knob()
    prior_min_step_px: float = knob(ge=0.0)
    prior_heading_threshold_rad: float = knob(ge=0.0)
    prior_min_run_frames: int = knob(ge=1)
    prior_smoothing_links: int = knob(ge=1)
    prior_scale_threshold: float = knob(ge=0.0)
    prior_min_scale_links: int = knob(ge=1)
    prior_noise_tolerance: float = knob(gt=0.0)
    progressive_revisits: bool = knob()
    revisit_window_m: float = knob(ge=0.0)
    search_sigmas: float = knob(ge=0.0)
    search_floor_px: float = knob(ge=0.0)
    coarse_max_pixels: int = knob(ge=1)
    coarse_window_px: int = knob(ge=0)  # 0 = always the whole overlap
    coarse_min_side_px: int = knob(ge=1)
    coarse_peaks: int = knob(ge=1)
    coarse_smoothing_px: float = knob(ge=0.0)  # 0 = pure phase correlation
    coarse_whitening_floor: float = knob(ge=0.0)
    coarse_taper_px: float = knob(ge=0.0)
    coarse_exclusion_px: float = knob(ge=0.0)
    max_iterations: int = knob(ge=1)
    tolerance_px: float = knob(ge=0.0)
    mask_margin_px: int = knob(ge=0)
    fine_stride_px: int = knob(ge=1)
    fine_smoothing_px: float = knob(ge=0.0)  # 0 = none
    fine_background_px: float = knob(ge=0.0)  # 0 = off
    fine_ramp: bool = knob()
    fine_max_step_px: float = knob(gt=0.0)
    min_overlap_fraction: float = knob(**FRACTION)
    min_overlap_px: int = knob(ge=0)
    covariance_inflation: float = knob(gt=0.0)
    feature_rotation_rad: float = knob(ge=0.0)
    feature_ratio: float = knob(gt=0.0, le=1.0)
    feature_max_error_px: float = knob(gt=0.0)
    feature_min_inliers: int = knob(ge=1)
    min_peak_z: float = knob(ge=0.0)
    min_peak_ncc: float = knob(**NCC)
    min_uniqueness: float = knob(ge=0.0, le=2.0)  # C1 - C2
    min_ncc: float = knob(**NCC)
    peak_null_pairs: int = knob(ge=0)  # 0 = off
    peak_null_min_pairs: int = knob(ge=0)
    peak_null_sigmas: float = knob(ge=0.0)
    peak_null_far_diagonals: float = knob(gt=0.0)
    map_link_stride: int = knob(ge=1)
    map_start_sigma_m: float = knob(gt=0.0)
    map_start_sigma_rad: float = knob(gt=0.0)
    map_min_covered_fraction: float = knob(**FRACTION)
    map_max_failed_anchors: int = knob(ge=0)  # 0 = never stop early
    pairs_per_task: int = knob(ge=1)
    workers: int = knob(ge=0)  # 0 = one per core (threads: only for frames of threads_min_frame_px)
    threads_min_frame_px: int = knob(ge=0)
    processes_min_frames: int = knob(ge=0)
    scheduler: str = knob(choices=SCHEDULER + ("auto",), url_schemes=SCHEDULER_URLS)
