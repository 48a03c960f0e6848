"""`make demo` as a newcomer sees it: a header line per step, no --quiet, and output that
keeps moving: its first steps (on a smaller floor), run off a terminal, print a line at least
every 10 seconds."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MAX_SILENCE_S = 10.0


def demo_recipe() -> list[str]:
    """The recipe lines of the Makefile's ``demo`` target (tabs and ``@`` stripped)."""
    lines, inside = [], False
    for line in (REPO / "Makefile").read_text().splitlines():
        if line.startswith("demo:"):
            inside = True
            continue
        if inside:
            if not line.startswith("\t"):
                break
            lines.append(line[1:].lstrip("@"))
    return lines


def test_every_demo_step_has_a_header_and_nothing_is_quiet():
    recipe = demo_recipe()
    assert recipe and recipe[0].startswith("rm -rf")
    headers = [m for line in recipe for m in re.findall(r'^echo "== step (\d+)/(\d+): (.+)"$', line)]
    total = int(headers[0][1])
    assert [int(n) for n, _, _ in headers] == list(range(1, total + 1))
    assert all(int(t) == total for _, t, _ in headers)
    # a header before the first command, and every command in some step
    first_cmd = next(i for i, line in enumerate(recipe) if "$(BIN)" in line)
    assert recipe[first_cmd - 1].startswith('echo "== step 1/')
    for line in recipe:
        assert "--quiet" not in line and " -q" not in line, line
    # pip is not silenced for a minute either
    install = (REPO / "Makefile").read_text().split("$(VENV)/.installed:", 1)[1].split("\n\n", 1)[0]
    assert "pip install -q" not in install and "echo" in install


def _command(line: str, demo: Path) -> list[str]:
    """A recipe line as a command run with this interpreter over a checkout."""
    line = line.replace("$(DEMO)", str(demo))
    args = shlex.split(line)
    if args[0] == "$(BIN)/mosaicmap":
        return [sys.executable, "-m", "pipeline.cli", *args[1:]]
    if args[0] == "$(BIN)/python":
        return [sys.executable, *args[1:]]
    raise AssertionError(f"unexpected demo command {line!r}")


@pytest.mark.slow
def test_demo_first_steps_print_a_line_at_least_every_10_s_off_a_terminal(tmp_path):
    """Steps 1 and 2 (simulate day 1, build it) on a 2 x 2 m floor, stdout and stderr a pipe:
    the longest gap between two lines stays under 10 s (progress lines, stage lines)."""
    recipe = demo_recipe()
    start = recipe.index(next(x for x in recipe if x.startswith('echo "== step 1/')))
    stop = recipe.index(next(x for x in recipe if x.startswith('echo "== step 3/')))
    stamps: list[tuple[float, str]] = []
    t0 = time.monotonic()
    for line in recipe[start:stop]:
        if line.startswith("echo "):
            stamps.append((time.monotonic() - t0, shlex.split(line)[1]))
            continue
        cmd = _command(line, tmp_path / "demo")
        if cmd[3:5] == ["simulate", "floor"]:
            cmd[cmd.index("--area") + 1] = "2x2"
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
        for out in proc.stdout:
            stamps.append((time.monotonic() - t0, out.rstrip("\n")))
        assert proc.wait() == 0, "\n".join(s for _, s in stamps)
    text = "\n".join(s for _, s in stamps)
    assert "\r" not in text  # no terminal bar in a log
    assert re.search(r"^ingest: done in .*frames accepted$", text, re.M)
    assert re.search(r"^publish: done in .* tag day1 on main$", text, re.M)
    assert "libpng" not in text and "not safe for concurrent" not in text
    assert not re.search(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", text, re.M)  # no time-stamped log lines
    gaps = [(b[0] - a[0], a[1], b[1]) for a, b in zip(stamps, stamps[1:])]
    worst = max(gaps)
    assert worst[0] < MAX_SILENCE_S, f"{worst[0]:.1f} s of silence between {worst[1]!r} and {worst[2]!r}"
