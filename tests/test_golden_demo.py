"""A small demo's bytes, recorded: a refactor that changes a map chunk, a pose or a link fails here.

Two days of a simulated 1.5 x 1.5 m floor (fixed seeds) are built into a map, as the demo
does; the content hashes of every stage output that decides the map (the links found, the
links kept, the optimized poses) and of every array of both published versions (data,
shape and dtype: no attributes, which hold random ids and dates) are compared with
``tests/golden/demo.json``. Floating-point results depend on the libraries' versions and on
the vector instructions the processor offers them (OpenCV's and numpy's sums, FFTs and
filters take other paths with AVX-512 than with AVX2), so the comparison runs only on a
machine matching one of the recordings there (skipped, saying so, elsewhere); record again
after a change that is meant to change the bytes (a recording for this machine replaces the
one of the same libraries and instructions, the others are kept):

    python tests/test_golden_demo.py --record
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).resolve().parent / "golden" / "demo.json"
STAGE_FILES = ("register/links.csv", "optimize/links.csv", "optimize/poses.csv")
LIBRARIES = ("numpy", "opencv-contrib-python-headless", "zarr", "icechunk", "gtsam", "OpenImageIO")


def library_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "absent"
    return out


# Instruction-set extensions whose presence changes which code paths the libraries take.
SIMD_PREFIXES = ("SSE", "AVX", "FMA", "F16C", "ASIMD", "NEON", "SVE", "VSX")


def simd_features() -> list[str]:
    """The vector instruction sets numpy finds on this processor (OpenCV dispatches on the same)."""
    from numpy._core._multiarray_umath import __cpu_features__

    return sorted(k for k, v in __cpu_features__.items() if v and k.startswith(SIMD_PREFIXES))


def machine() -> dict:
    """What a recording's bytes depend on besides the code: library versions, vector instructions."""
    return {"libraries": library_versions(), "simd": simd_features()}


def _array_hashes(group, prefix: str = "") -> dict[str, str]:
    import zarr

    out = {}
    for name, item in sorted(group.members()):
        path = f"{prefix}{name}"
        if isinstance(item, zarr.Array):
            data = np.ascontiguousarray(item[...])
            h = hashlib.sha256(f"{data.dtype.str}{data.shape}".encode())
            h.update(data.tobytes())
            out[path] = h.hexdigest()
        else:
            out.update(_array_hashes(item, path + "/"))
    return out


def build_and_hash(root: Path) -> dict[str, str]:
    """Simulate and build the two days in ``root``; {name: sha256} of what they made."""
    from conftest import invoke
    from mapstore.repository import MapRepository

    import zarr

    steps = [("simulate", "floor", root / "day1", "--seed", 3, "--area", "1.5x1.5", "--quiet"),
             ("simulate", "floor", root / "day2", "--seed", 4, "--area", "1.5x1.5", "--world", root / "day1",
              "--changes", 1, "--quiet"),
             ("build", root / "day1", "--map", root / "map", "-w", root / "w1", "--tag", "day1", "--quiet"),
             ("build", root / "day2", "--map", root / "map", "-w", root / "w2", "--tag", "day2", "--quiet")]
    for args in steps:
        r = invoke(*args)
        assert r.exit_code == 0, r.output
    out = {}
    for day in ("w1", "w2"):
        for f in STAGE_FILES:
            out[f"{day}/{f}"] = hashlib.sha256((root / day / f).read_bytes()).hexdigest()
    repo = MapRepository.open(str(root / "map"))
    for tag in ("day1", "day2"):
        group = zarr.open_group(repo.readonly(tag).store, mode="r")
        out.update({f"{tag}:{k}": v for k, v in _array_hashes(group).items()})
    return out


def test_the_demo_builds_the_recorded_bytes(tmp_path):
    if not GOLDEN.exists():
        pytest.skip(f"{GOLDEN.name} not recorded (python tests/test_golden_demo.py --record)")
    here = machine()
    match = [r for r in json.loads(GOLDEN.read_text())["recordings"] if r["machine"] == here]
    if not match:
        pytest.skip(f"no recording for {here}: floating-point results may differ between library versions "
                    "and vector instruction sets (python tests/test_golden_demo.py --record)")
    got = build_and_hash(tmp_path)
    want = match[0]["hashes"]
    assert sorted(got) == sorted(want), "the demo's outputs changed: " + ", ".join(sorted(set(got) ^ set(want)))
    differ = [k for k in want if got[k] != want[k]]
    assert not differ, f"{len(differ)} of {len(want)} outputs differ from the recording, e.g. {differ[:5]}"


if __name__ == "__main__":  # python tests/test_golden_demo.py --record
    import tempfile

    if sys.argv[1:] != ["--record"]:
        raise SystemExit("usage: python tests/test_golden_demo.py --record")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    with tempfile.TemporaryDirectory() as d:
        hashes = build_and_hash(Path(d))
    GOLDEN.parent.mkdir(exist_ok=True)
    here = machine()
    kept = [r for r in json.loads(GOLDEN.read_text())["recordings"] if r["machine"] != here] if GOLDEN.exists() else []
    recordings = kept + [{"machine": here, "hashes": hashes}]
    GOLDEN.write_text(json.dumps({"recordings": recordings}, indent=1, sort_keys=True) + "\n")
    print(f"recorded {len(hashes)} hashes in {GOLDEN}")
