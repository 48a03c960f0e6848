"""The nightly cycle on a real S3-compatible server (versitygw on loopback, see
``scripts/s3_server.sh``): maps at ``s3://BUCKET/PREFIX`` with the endpoint and
credentials from the environment, as a site would run it.

Two versions built and published, log, tag, rollback, diff, export, verify, and a
vehicle tracking from the exported bundle; two builds publishing on one branch at once
(one publishes, the other exits 1 asking for a rerun, and the rerun loses nothing); a
wrong credential or an unreachable endpoint is one line and exit 2.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest
import zarr

from mapstore.layout import read_floor, read_poses
from mapstore.repository import MapRepository
from s3_server import REPO, free_port, running_server, server_binary
from conftest import invoke, SMALL_MAP_TOML as SMALL

pytestmark = pytest.mark.s3


def run_cli(*args, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    """``mosaicmap ARGS`` in a process of its own (its own environment, stderr apart)."""
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=REPO, timeout=timeout)


def cli_env(server, **override) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    env.update(server.env)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    env.update(override)
    return env


@pytest.fixture(scope="module")
def s3():
    """A server for this module, its client environment set in this process."""
    if server_binary() is None:
        pytest.skip("no S3 server installed (run: scripts/s3_server.sh install)")
    with running_server() as server, pytest.MonkeyPatch.context() as mp:
        for k in [k for k in os.environ if k.startswith("AWS_")]:
            mp.delenv(k)
        for k, v in server.env.items():
            mp.setenv(k, v)
        yield server


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """Day 1, day 2 (the same floor, two changes, darker), a vehicle's run on day 2's floor,
    and two more logs of day 1's floor for two builds at once."""
    root = tmp_path_factory.mktemp("s3-logs")
    cfg = root / "small.toml"
    cfg.write_text(SMALL)
    out = {"root": root, "cfg": cfg}
    plans = {
        "day1": ("--area", "1.5x1.5", "--seed", "5"),
        "day2": ("--world", "{day1}", "--route", "loop", "--changes", "2", "--seed", "6", "--illumination", "0.8"),
        "ops": ("--world", "{day2}", "--route", "loop", "--noise", "10", "--seed", "30"),
        "day3a": ("--world", "{day1}", "--route", "loop", "--seed", "7"),
        "day3b": ("--world", "{day1}", "--route", "loop", "--seed", "8"),
    }
    for name, args in plans.items():
        out[name] = root / name
        r = invoke("simulate", "floor", out[name], *[a.format(**out) for a in args], "--quiet")
        assert r.exit_code == 0, r.output
    return out


def _versions(url: str) -> list[int]:
    """The map versions along the main branch, newest first."""
    repo = MapRepository.open(url)
    return [int((si.metadata or {}).get("version", 0)) for si in repo.repo.ancestry(branch="main")
            if (si.metadata or {}).get("version")]


def test_nightly_cycle_on_s3(s3, logs, tmp_path):
    url, cfg = s3.url("site-a"), logs["cfg"]
    for day in ("day1", "day2"):
        r = invoke("build", logs[day], "--map", url, "-w", tmp_path / f"w-{day}", "--config", cfg,
                   "--report", tmp_path / f"{day}.json", "--tag", day, "--quiet")
        assert r.exit_code == 0, r.output
    rep2 = json.loads((tmp_path / "day2.json").read_text())
    assert rep2["publish"]["version"] == 2 and rep2["map"]["base_version"] == 1

    # the objects are on the server, under the prefix (not in some local directory)
    repo = MapRepository.open(url)
    assert set(repo.tags()) >= {"day1", "day2"} and _versions(url) == [2, 1]
    root = zarr.open_group(repo.readonly("day2").store, mode="r")
    assert read_floor(root).version == 2 and len(read_poses(root).sources) == 2

    r = invoke("log", url)
    assert r.exit_code == 0, r.output
    lines = r.output.strip().splitlines()
    assert "day2" in lines[0] and "day1" in lines[1]

    r = invoke("tag", url, "day1", "first-night")
    assert r.exit_code == 0, r.output
    assert MapRepository.open(url).tags()["first-night"] == MapRepository.open(url).tags()["day1"]

    r = invoke("diff", url, "day1", "day2", "--out", tmp_path / "diff", "--report", tmp_path / "diff.json", "--quiet")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "diff" / "diff.html").is_file()
    assert json.loads((tmp_path / "diff.json").read_text())["regions"]

    key = tmp_path / "keys" / "owner.key"
    assert invoke("keys", "new", key).exit_code == 0
    bundle = tmp_path / "day2.zip"
    r = invoke("export", url, bundle, "--version", "day2", "--sign", key, "--quiet")
    assert r.exit_code == 0, r.output
    r = invoke("verify", bundle, "--key", f"{key}.pub")
    assert r.exit_code == 0, r.output
    r = invoke("track", bundle, logs["ops"], "--key", f"{key}.pub", "--report", tmp_path / "track.json", "--quiet")
    assert r.exit_code == 0, r.output
    track = json.loads((tmp_path / "track.json").read_text())
    assert track["fixes"] > 0 and track["ok_rate"] > 0.5, track

    r = invoke("rollback", url, "day1")
    assert r.exit_code == 0, r.output
    repo = MapRepository.open(url)
    saved = [t for t in repo.tags() if t.startswith("rollback-from-")]
    assert repo.resolve("latest") == repo.tags()["day1"] and len(saved) == 1
    assert repo.tags()[saved[0]] == repo.tags()["day2"]  # the rolled-back version is kept

    # garbage collection on the bucket frees nothing a tag or branch reaches
    r = invoke("gc", url, "--older-than", "0")
    assert r.exit_code == 0, r.output
    root = zarr.open_group(MapRepository.open(url).readonly("day2").store, mode="r")
    assert read_floor(root).version == 2 and root["floor/0"][...].any()


def test_two_builds_publishing_at_once(s3, logs, tmp_path):
    """Both read version 1; one publishes version 2, the other exits 1 asking for a rerun; its
    rerun publishes version 3 on top: no version lost."""
    url, cfg = s3.url("site-b"), logs["cfg"]
    r = invoke("build", logs["day1"], "--map", url, "-w", tmp_path / "w1", "--config", cfg, "--quiet")
    assert r.exit_code == 0, r.output
    env = cli_env(s3)
    procs = {name: subprocess.Popen([sys.executable, "-m", "pipeline.cli", "build", str(logs[name]), "--map", url,
                                     "-w", str(tmp_path / f"w-{name}"), "--config", str(cfg), "--tag", name,
                                     "--quiet"],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
             for name in ("day3a", "day3b")}
    results = {name: (p.wait(timeout=600), p.stderr.read()) for name, p in procs.items()}
    for p in procs.values():
        p.stdout.close()
        p.stderr.close()
    codes = sorted(code for code, _ in results.values())
    assert codes == [0, 1], results
    winner = next(n for n, (code, _) in results.items() if code == 0)
    loser = next(n for n, (code, _) in results.items() if code == 1)
    err = results[loser][1].strip()
    assert len(err.splitlines()) == 1 and "rerun the build" in err and "Traceback" not in err, err

    repo = MapRepository.open(url)
    assert winner in repo.tags() and loser not in repo.tags() and _versions(url) == [2, 1]
    p = run_cli("build", logs[loser], "--map", url, "-w", tmp_path / f"w-{loser}", "--config", cfg, "--tag", loser,
                "--quiet", env=env)
    assert p.returncode == 0, p.stderr
    repo = MapRepository.open(url)
    assert _versions(url) == [3, 2, 1]
    assert [repo.resolve(t) for t in (loser, winner)] == [si.id for si in repo.repo.ancestry(branch="main")][:2]
    root = zarr.open_group(repo.readonly().store, mode="r")
    assert {s["log_id"] for s in read_poses(root).sources} == {"day1", "day3a", "day3b"}


def _one_line_error(p: subprocess.CompletedProcess) -> str:
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mosaicmap: error: ") and "Traceback" not in p.stderr, p.stderr
    return lines[0]


def test_a_wrong_credential_is_one_line_exit_2(s3, logs, tmp_path):
    url = s3.url("site-c")
    r = invoke("build", logs["day1"], "--map", url, "-w", tmp_path / "w", "--config", logs["cfg"], "--until",
               "ingest", "--quiet")
    assert r.exit_code == 0, r.output
    MapRepository.create(url)
    for override in ({"AWS_SECRET_ACCESS_KEY": "not-the-secret"}, {"AWS_ACCESS_KEY_ID": "nobody"}):
        env = cli_env(s3, **override)
        for args in (("log", url), ("build", logs["day1"], "--map", url, "-w", tmp_path / "w", "--config",
                                    logs["cfg"], "--quiet")):
            p = run_cli(*args, env=env)
            line = _one_line_error(p)
            assert p.returncode == 2 and "refused the credentials" in line and url in line, (args, line)


def test_an_unreachable_endpoint_is_one_line_exit_2_at_once(s3, logs, tmp_path):
    url = s3.url("site-d")
    env = cli_env(s3, AWS_ENDPOINT_URL=f"http://127.0.0.1:{free_port()}")
    for args in (("log", url), ("build", logs["day1"], "--map", url, "-w", tmp_path / "w", "--config", logs["cfg"],
                                "--quiet")):
        t0 = time.monotonic()
        p = run_cli(*args, env=env)
        line = _one_line_error(p)
        assert p.returncode == 2 and "cannot reach" in line and url in line, (args, line)
        assert time.monotonic() - t0 < 30, "waited for icechunk's retries"


def test_a_missing_bucket_is_one_line_exit_2(s3, tmp_path):
    p = run_cli("log", "s3://no-such-bucket/site", env=cli_env(s3))
    line = _one_line_error(p)
    assert p.returncode == 2 and "does not exist" in line, line


def test_the_server_refuses_a_stale_conditional_write(s3, tmp_path):
    """What makes a second committer fail: the server honours If-None-Match: * (create only)
    and If-Match: ETag (replace only that version) on PUT, answering 412 otherwise."""
    import shutil

    if shutil.which("curl") is None:
        pytest.skip("curl absent")
    body = tmp_path / "body"
    body.write_text("ref")

    def put(header: str) -> str:
        return subprocess.run(
            ["curl", "-s", "-o", "/dev/null", "-w", "%{http_code}", "--aws-sigv4", "aws:amz:us-east-1:s3",
             "--user", f"{s3.env['AWS_ACCESS_KEY_ID']}:{s3.env['AWS_SECRET_ACCESS_KEY']}",
             "-H", "x-amz-content-sha256: UNSIGNED-PAYLOAD", "-H", header, "-T", str(body),
             f"{s3.endpoint}/{s3.bucket}/probe/ref.json"], capture_output=True, text=True, timeout=30).stdout

    assert put("If-None-Match: *") == "200"
    assert put("If-None-Match: *") == "412"
    assert put('If-Match: "not-its-etag"') == "412"
