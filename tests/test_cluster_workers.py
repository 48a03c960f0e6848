"""Register and render on dask.distributed worker *processes* (``--scheduler tcp://...``).

A cluster of two single-threaded worker processes shares the work directory on local disk
with the build; what it writes must be the bytes the in-process ``threads`` scheduler
writes: links, poses and every array of the published map. A worker killed in the middle
of the render is replaced and its task rerun (dask's retry), and the build still completes
with the same map.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path

import pytest
import zarr

from mapstore.repository import MapRepository
from conftest import invoke, SMALL_MAP_TOML as SMALL

pytestmark = pytest.mark.cluster


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes (nannies) of one thread each, on loopback."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      host="127.0.0.1") as c:
        yield c


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A simulated floor built on the ``threads`` scheduler: the bytes to match."""
    root = tmp_path_factory.mktemp("cluster")
    cfg = root / "small.toml"
    cfg.write_text(SMALL)
    day1 = root / "day1"
    r = invoke("simulate", "floor", day1, "--area", "1.5x1.5", "--seed", "5", "--quiet")
    assert r.exit_code == 0, r.output
    r = invoke("build", day1, "--map", root / "map-threads", "-w", root / "w-threads", "--config", cfg,
               "--scheduler", "threads", "--quiet")
    assert r.exit_code == 0, r.output
    return {"root": root, "cfg": cfg, "day1": day1, "map": root / "map-threads", "work": root / "w-threads"}


def _arrays(group: zarr.Group, prefix: str = "") -> dict[str, zarr.Array]:
    """Every array under ``group``, by path."""
    out = {}
    for name, member in group.members():
        path = f"{prefix}{name}"
        if isinstance(member, zarr.Array):
            out[path] = member
        else:
            out.update(_arrays(member, path + "/"))
    return out


def assert_same_build(ref: dict, work: Path, repo: Path) -> None:
    """Links and poses files byte for byte, and every array of the published map the same
    bytes (dtype, shape and decoded contents, NaN cells included)."""
    for rel in ("register/links.csv", "optimize/poses.csv"):
        assert (work / rel).read_bytes() == (ref["work"] / rel).read_bytes(), rel
    got = zarr.open_group(MapRepository.open(str(repo)).readonly().store, mode="r")
    want = zarr.open_group(MapRepository.open(str(ref["map"])).readonly().store, mode="r")
    a, b = _arrays(got), _arrays(want)
    assert sorted(a) == sorted(b) and "floor/0" in a
    for path in b:
        assert a[path].dtype == b[path].dtype and a[path].shape == b[path].shape, path
        assert a[path][...].tobytes() == b[path][...].tobytes(), f"{path} differs"


def test_worker_processes_write_the_threads_bytes(reference, cluster, tmp_path):
    """register and render on two worker processes over a shared work directory."""
    work, repo = tmp_path / "w", tmp_path / "map"
    r = invoke("build", reference["day1"], "--map", repo, "-w", work, "--config", reference["cfg"],
               "--scheduler", cluster.scheduler_address, "--quiet")
    assert r.exit_code == 0, r.output
    assert_same_build(reference, work, repo)


@contextmanager
def cluster_killing_first_render_task(flag: Path, allowed_failures: int = 3):
    """A fresh two-process cluster whose worker starting the first level-0 render task dies
    on the spot (``os._exit``: no cleanup, as a kill -9), once (``flag`` records it).
    ``allowed_failures``: the scheduler's retries of a task whose worker died."""
    import dask
    from distributed import Client, LocalCluster, WorkerPlugin

    class KillFirstRenderTask(WorkerPlugin):
        def __init__(self, flag: str):
            self.flag = flag

        def transition(self, key, start, finish, **kwargs):
            name = key[0] if isinstance(key, tuple) else str(key)
            if finish == "executing" and str(name).startswith("_level0_task"):
                try:
                    os.close(os.open(self.flag, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                except FileExistsError:
                    return
                os._exit(9)

    with dask.config.set({"distributed.scheduler.allowed-failures": allowed_failures}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                         host="127.0.0.1") as c, Client(c) as client:
        client.register_plugin(KillFirstRenderTask(str(flag)), name="kill-first-render-task")
        yield c.scheduler_address


def test_a_worker_killed_mid_render_is_replaced_and_the_build_completes(reference, tmp_path):
    """The dead worker's nanny starts a new one, the scheduler reruns the lost task: the
    build completes with the same bytes."""
    flag, work, repo = tmp_path / "killed", tmp_path / "w", tmp_path / "map"
    with cluster_killing_first_render_task(flag) as address:
        r = invoke("build", reference["day1"], "--map", repo, "-w", work, "--config", reference["cfg"],
                   "--scheduler", address, "--quiet")
    assert flag.exists(), "no render task ran on the cluster"
    assert r.exit_code == 0, r.output
    assert_same_build(reference, work, repo)


def test_a_task_whose_workers_keep_dying_fails_in_one_line_and_the_rerun_resumes(reference, tmp_path):
    """No retry allowed: the build exits 1 with one line naming the task, publishes nothing,
    keeps its finished stages; the rerun redoes the render only and writes the same bytes."""
    flag, work, repo = tmp_path / "killed", tmp_path / "w", tmp_path / "map"
    with cluster_killing_first_render_task(flag, allowed_failures=0) as address:
        r = invoke("build", reference["day1"], "--map", repo, "-w", work, "--config", reference["cfg"],
                   "--scheduler", address, "--quiet")
        assert flag.exists() and r.exit_code == 1, r.output
        # the stages that finished printed their lines as they finished; the error is one line
        *done, error = r.output.strip().splitlines()
        assert all(ln.split(":")[0] in ("ingest", "register", "optimize") for ln in done), r.output
        assert error.startswith("mosaicmap: error:") and "_level0_task" in error and "rerun the build" in error, r.output
        assert not (work / "render" / "manifest.json").exists() and (work / "optimize" / "manifest.json").exists()
        assert not MapRepository.exists(str(repo))  # nothing published
        r = invoke("build", reference["day1"], "--map", repo, "-w", work, "--config", reference["cfg"],
                   "--scheduler", address)
    assert r.exit_code == 0, r.output
    assert "register: skipped" in r.output and "render: done" in r.output, r.output
    assert_same_build(reference, work, repo)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_scheduler_killed_mid_render_fails_in_one_line_and_the_rerun_resumes(reference, cluster, tmp_path):
    """A ``dask scheduler`` process killed (SIGKILL) while the first level-0 render task
    runs: the build exits 1 with one line (no traceback, no log noise from distributed),
    publishes nothing and keeps its finished stages; the rerun on another scheduler redoes
    the render only and writes the reference bytes."""
    import signal
    import subprocess
    import sys
    import time

    from distributed import Client, WorkerPlugin

    class KillScheduler(WorkerPlugin):
        def __init__(self, pid: int, flag: str):
            self.pid, self.flag = pid, flag

        def transition(self, key, start, finish, **kwargs):
            name = key[0] if isinstance(key, tuple) else str(key)
            if finish == "executing" and str(name).startswith("_level0_task") and not os.path.exists(self.flag):
                open(self.flag, "w").close()
                os.kill(self.pid, signal.SIGKILL)

    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                         os.environ.get("PYTHONPATH", "")]))
    quiet = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                              "--port", str(port), "--dashboard-address", ":0"], **quiet)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                               "--nworkers", "1", "--no-dashboard"], **quiet)
    flag, work, repo = tmp_path / "killed", tmp_path / "w", tmp_path / "map"
    try:
        with Client(address, timeout="60s") as c:
            c.wait_for_workers(1, timeout=60)
            c.register_plugin(KillScheduler(sched.pid, str(flag)), name="kill-scheduler")
        t0 = time.monotonic()
        r = invoke("build", reference["day1"], "--map", repo, "-w", work, "--config", reference["cfg"],
                   "--scheduler", address, "--quiet")
    finally:
        worker.kill()
        sched.kill()
        worker.wait()
        sched.wait()
    assert flag.exists() and r.exit_code == 1, r.output
    assert time.monotonic() - t0 < 120
    *done, error = r.output.strip().splitlines()
    assert all(ln.split(":")[0] in ("ingest", "register", "optimize") for ln in done), r.output
    assert error.startswith("mosaicmap: error: dask scheduler") and "lost the connection" in error, r.output
    assert "rerun the build" in error and "Traceback" not in r.output, r.output
    assert not (work / "render" / "manifest.json").exists() and (work / "optimize" / "manifest.json").exists()
    assert not MapRepository.exists(str(repo))
    r = invoke("build", reference["day1"], "--map", repo, "-w", work, "--config", reference["cfg"],
               "--scheduler", cluster.scheduler_address)
    assert r.exit_code == 0, r.output
    assert "register: skipped" in r.output and "render: done" in r.output, r.output
    assert_same_build(reference, work, repo)
