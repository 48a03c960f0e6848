"""A real S3-compatible server for tests: versitygw over a temporary directory, on loopback,
started and stopped by ``scripts/s3_server.sh`` (which also installs it; see there)."""

from __future__ import annotations

import os
import socket
import subprocess
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "s3_server.sh"
BUCKET = "mosaicmap"


@dataclass(frozen=True)
class S3Server:
    """A running server: ``env`` is what a client needs (AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID,
    AWS_SECRET_ACCESS_KEY, AWS_REGION); maps go to ``s3://{bucket}/PREFIX``."""

    endpoint: str
    bucket: str
    env: dict[str, str]

    def url(self, prefix: str) -> str:
        return f"s3://{self.bucket}/{prefix}"


def server_binary() -> str | None:
    """The installed server's path, or None when ``scripts/s3_server.sh install`` has not run."""
    p = subprocess.run(["bash", str(SCRIPT), "path"], capture_output=True, text=True)
    return p.stdout.strip() if p.returncode == 0 else None


def free_port() -> int:
    """A TCP port nothing listens on now (loopback)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _parse_exports(text: str) -> dict[str, str]:
    env = {}
    for line in text.splitlines():
        if line.startswith("export "):
            k, _, v = line[len("export "):].partition("=")
            env[k] = v
    return env


@contextmanager
def running_server(port: int | None = None) -> Iterator[S3Server]:
    """Start a server on 127.0.0.1 (a free port unless given) with bucket :data:`BUCKET`;
    stop it, and delete its data, on exit."""
    port = port or free_port()
    env = dict(os.environ, S3_PORT=str(port), S3_BUCKET=BUCKET)
    p = subprocess.run(["bash", str(SCRIPT), "start"], capture_output=True, text=True, env=env, timeout=60)
    if p.returncode != 0:
        raise RuntimeError(f"s3_server.sh start failed: {p.stderr.strip()}")
    try:
        client = _parse_exports(p.stdout)
        yield S3Server(endpoint=client["AWS_ENDPOINT_URL"], bucket=BUCKET, env=client)
    finally:
        subprocess.run(["bash", str(SCRIPT), "stop"], capture_output=True, text=True, env=env, timeout=60)
