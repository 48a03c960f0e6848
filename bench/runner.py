"""Running benchmark steps in fresh child processes (shared by bench/*.py).

A child measures its own wall time and peak RSS (:mod:`peak_memory`), so a benchmark's
figures do not include the parent's imports and memory.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from peak_memory import CHILD_PRELUDE

__all__ = ["REPO", "COMMAND", "compile_sources", "child_env", "child", "run_cli", "mosaicmap", "reusable"]

REPO = Path(__file__).resolve().parents[1]

# A mosaicmap command in a child: its wall time, import time and its own peak RSS.
COMMAND = r"""
import json, sys, time
t0 = time.perf_counter()
from peak_memory import hwm_kb
from pipeline.cli import cli
t1 = time.perf_counter()
rc = cli.main(sys.argv[1:], prog_name="mosaicmap", standalone_mode=False)
if rc:
    sys.exit(rc)
print(json.dumps({"wall_seconds": time.perf_counter() - t1, "import_seconds": t1 - t0, "hwm_mb": hwm_kb() / 1024.0}))
"""


_COMPILED = False


def compile_sources() -> None:
    """Write the bytecode of this checkout's packages (once per run; quick when it is current).

    An installed package has its bytecode written at install (pip compiles wheels) or at its
    first import; a checkout run under ``PYTHONDONTWRITEBYTECODE`` (or ``-B``) would compile
    every module in every child, ~0.5-0.7 s a command on 2 cores, a cost the peers' installed
    packages never pay. ``py_compile`` writes regardless of that setting, and a cached file is
    read whatever it says.
    """
    global _COMPILED
    if not _COMPILED:
        import compileall

        for pkg in ("pipeline", "mapstore", "tracker"):
            compileall.compile_dir(REPO / pkg, quiet=1)
        _COMPILED = True


def child_env() -> dict:
    """The environment of a child: this checkout first on PYTHONPATH (its bytecode compiled:
    :func:`compile_sources`)."""
    compile_sources()
    return dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def child(code: str, *args, prelude: bool = True) -> dict:
    """Run ``code`` in a fresh interpreter; its last stdout line as JSON."""
    p = subprocess.run([sys.executable, "-c", (CHILD_PRELUDE if prelude else "") + code, *map(str, args)],
                       capture_output=True, text=True, cwd=REPO, env=child_env())
    if p.returncode != 0:
        raise RuntimeError(f"child failed ({p.returncode}):\n{p.stderr[-4000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def run_cli(*args) -> str:
    """A mosaicmap command (simulate, build, ...) in a child; its output; raises on failure."""
    p = subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], capture_output=True, text=True,
                       cwd=REPO, env=child_env())
    if p.returncode != 0:
        raise RuntimeError(f"mosaicmap {' '.join(map(str, args[:2]))} failed ({p.returncode}):\n"
                           f"{(p.stdout + p.stderr)[-4000:]}")
    return p.stdout


def mosaicmap(report: Path, *args, quiet: bool = True) -> dict:
    """A mosaicmap command in a child writing ``report``: the report plus the child's wall
    time, import time and peak RSS (``wall_seconds``, ``import_seconds``, ``hwm_mb``)."""
    run = child(COMMAND, *args, "--report", report, *(["--quiet"] if quiet else []))
    return {**json.loads(Path(report).read_text()), **run}


def reusable(marker: Path, params: dict, reuse: bool) -> bool:
    """Whether kept data may be reused (``--reuse``): ``marker`` (JSON written when the data
    was made, holding ``{"params": ...}``) exists with the same ``params``."""
    return reuse and marker.exists() and json.loads(marker.read_text()).get("params") == params
