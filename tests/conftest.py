"""Shared fixtures: small hand-made drive logs (independent of the simulator) and paths."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.drivelog import CameraSpec, write_drive_log
from pipeline.images import write_grey

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REAL_DATA = SHARED / "data" / "real"


def modules_pulled_in(imports: list[str], packages: tuple[str, ...]) -> list[str]:
    """The modules of ``packages`` that importing ``imports`` in a fresh interpreter loads
    (what a layering rule forbids: e.g. tracker must not pull in pipeline)."""
    import os
    import subprocess
    import sys

    code = (f"import sys, {', '.join(imports)}; "
            f"print(','.join(sorted(m for m in sys.modules if m.split('.')[0] in {packages!r})))")
    p = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    out = p.stdout.strip()
    return out.split(",") if out else []


def smooth_texture(rng: np.random.Generator, shape: tuple[int, int], mean: float = 128.0, std: float = 30.0) -> np.ndarray:
    """A band-limited random texture in grey levels (float32)."""
    acc = np.zeros(shape, np.float32)
    for sigma, w in ((1.0, 1.0), (3.0, 0.7), (8.0, 0.5)):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        acc += w * layer / layer.std()
    return mean + std * acc / acc.std()


def write_small_log(
    path: Path,
    *,
    n_frames: int = 8,
    size: tuple[int, int] = (64, 48),
    seed: int = 0,
    camera: CameraSpec | None = None,
    bits: int = 8,
) -> Path:
    """A tiny valid drive log: textured frames, odometry at 20 Hz spanning the frames."""
    rng = np.random.default_rng(seed)
    camera = camera or CameraSpec(pixel_size_m=0.0025)
    (path / "images").mkdir(parents=True, exist_ok=True)
    w, h = size
    frame_t = 0.1 + 0.1 * np.arange(n_frames)
    names = []
    for i in range(n_frames):
        name = f"images/{i:06d}.png"
        write_grey(path / name, smooth_texture(rng, (h, w)), bits=bits)
        names.append(name)
    t = np.arange(0.0, frame_t[-1] + 0.1001, 0.05)
    odo = np.stack([t, 0.5 * t, 0.1 * t, 0.05 * t], axis=1)
    write_drive_log(path, camera, frame_t, names, odo, log_id=path.name)
    return path


@pytest.fixture
def small_log(tmp_path: Path) -> Path:
    return write_small_log(tmp_path / "log")


def require_real(name: str) -> Path:
    p = REAL_DATA / name
    if not p.exists():
        pytest.skip(f"real data {p} absent (../shared not checked out beside the repo)")
    return p


def bench_module(name: str):
    """The module ``bench/<name>.py`` (the benchmarks are scripts, not a package): imported
    with ``bench/`` on the path for the import only."""
    import importlib
    import sys

    sys.path.insert(0, str(REPO / "bench"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.pop(0)


SMALL_MAP_TOML = """
[map]
chunk_px = 64
shard_px = 256
layer_cell_px = 16
"""
"""A configuration override of small chunks and shards: a 1.5 m floor then spans several
shards and pyramid levels."""


def invoke(*args):
    """``mosaicmap ARGS`` in this process (click's CliRunner; arguments str()-ed), exceptions
    propagating: the result's exit_code and output."""
    from click.testing import CliRunner

    from pipeline.cli import cli

    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
