"""README.md as a user meets it: the quick start's commands and the "Read a map from Python"
snippet run exactly as written (parsed from the README's text), every relative link of the
user documentation resolves to a file (and heading) of the repository, and nothing in it
points outside the repository."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"

# The user documentation: what the README links to and what links back.
DOC_FILES = [README, REPO / "bench" / "README.md", REPO / "examples" / "README.md",
             *sorted((REPO / "docs").glob("*.md"))]

# The subcommands the quick start must walk through, in this order.
QUICK_START_STEPS = ["simulate", "build", "show", "quicklook", "keys", "export", "track"]


def section(text: str, title: str) -> str:
    """The body of the level-2 section ``## title`` (up to the next level-2 heading)."""
    m = re.search(rf"(?m)^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, re.S)
    assert m, f"README.md has no section '## {title}'"
    return m.group(1)


def code_blocks(text: str, lang: str) -> list[str]:
    """The fenced code blocks of ``text`` tagged ``lang``."""
    return re.findall(rf"(?ms)^```{lang}\n(.*?)^```", text)


def quick_start_commands() -> list[list[str]]:
    """The quick start's shell block as argument lists (comments dropped)."""
    blocks = code_blocks(section(README.read_text(), "Quick start"), "sh")
    assert len(blocks) == 1, "the quick start is one sh block"
    commands = [shlex.split(line, comments=True) for line in blocks[0].splitlines()]
    return [c for c in commands if c]


def run_mosaicmap(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``mosaicmap ARGS`` from this checkout, in ``cwd``, as a user's shell would run it."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def quick_start(tmp_path_factory) -> Path:
    """A fresh directory after every quick-start command ran in it (each must exit 0)."""
    d = tmp_path_factory.mktemp("quickstart")
    for argv in quick_start_commands():
        assert argv[0] == "mosaicmap", f"quick start line not a mosaicmap command: {argv}"
        r = run_mosaicmap(argv[1:], d)
        assert r.returncode == 0, f"{shlex.join(argv)} exited {r.returncode}:\n{r.stderr[-3000:]}"
    return d


def test_quick_start_walks_the_workflow():
    """Simulate, build, look, sign, export and track, in that order, on a small floor."""
    commands = quick_start_commands()
    steps = [c[1] for c in commands]
    positions = [steps.index(s) for s in QUICK_START_STEPS]
    assert positions == sorted(positions), steps
    sim = next(c for c in commands if c[1:3] == ["simulate", "floor"])
    area = sim[sim.index("--area") + 1]
    assert all(float(v) <= 3 for v in area.split("x")), f"quick start floor {area} m: keep it small"


@pytest.mark.slow
def test_quick_start_runs_as_written(quick_start):
    d = quick_start
    assert (d / "map").is_dir()
    for png in ("quicklook.png", "track.png"):
        assert (d / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    # the bundle the README exports is whole and signed by the key it made
    r = run_mosaicmap(["verify", "bundle.zip", "--key", "keys/owner.key.pub"], d)
    assert r.returncode == 0, r.stderr


@pytest.mark.slow
def test_python_snippet_reads_the_published_map(quick_start, monkeypatch, capsys):
    from mapstore.grid import MapGrid
    from mapstore.repository import MapRepository
    import zarr

    blocks = code_blocks(section(README.read_text(), "Read a map from Python"), "python")
    assert len(blocks) == 1
    monkeypatch.chdir(quick_start)
    ns: dict = {}
    exec(compile(blocks[0], "README.md (Read a map from Python)", "exec"), ns)
    assert "covered" in capsys.readouterr().out

    window, grid = ns["window"], MapGrid.from_attrs(ns["grid"])
    side = round(0.5 / grid.pixel_size)
    assert window.dtype == np.uint8 and window.shape == (side, side)
    assert (window > 0).mean() > 0.9, "the snippet's window lies on the simulated floor"
    # the same pixels as mapstore reads at the world position the snippet names
    col, row = grid.world_to_pixel(np.array(0.0), np.array(1.0))
    assert (ns["row"], ns["col"]) == (round(float(row)), round(float(col)))
    session = MapRepository.open(str(quick_start / "map")).readonly("day1")
    level0 = zarr.open_group(session.store, mode="r")["floor/0"]
    np.testing.assert_array_equal(window, level0[ns["row"]:ns["row"] + side, ns["col"]:ns["col"] + side])


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces -> '-'."""
    s = heading.strip().lower()
    s = re.sub(r"[^\w\- ]", "", s)
    return s.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown file (outside code blocks; repeats get -1, -2...)."""
    text = re.sub(r"(?ms)^```.*?^```", "", path.read_text())
    seen: dict[str, int] = {}
    out = set()
    for h in re.findall(r"(?m)^#{1,6} (.+)$", text):
        a = github_anchor(h)
        n = seen.get(a, 0)
        out.add(a if n == 0 else f"{a}-{n}")
        seen[a] = n + 1
    return out


def links(path: Path) -> list[str]:
    """The targets of the markdown links of a file (outside code blocks)."""
    text = re.sub(r"(?ms)^```.*?^```", "", path.read_text())
    return re.findall(r"\[[^\]]*\]\(([^)\s]+)\)", text)


@pytest.mark.parametrize("doc", DOC_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve_inside_the_repository(doc):
    bad = []
    for target in links(doc):
        if re.match(r"[a-z]+:", target):          # https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (doc.parent / file).resolve() if file else doc
        if not dest.is_relative_to(REPO) or not dest.exists():
            bad.append(f"{target}: no such file in the repository")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {dest.relative_to(REPO)}")
    assert not bad, f"{doc.relative_to(REPO)}: " + "; ".join(bad)


def test_readme_links_every_doc():
    text = README.read_text()
    for doc in sorted((REPO / "docs").glob("*.md")):
        assert f"(docs/{doc.name}" in text, f"README.md does not link docs/{doc.name}"
    assert "(bench/README.md)" in text


# Words that mean something only to the people who wrote the code, or point outside it.
OUTSIDE = re.compile(r"\.\./shared|MISSION\.md|\bissue \d+|\bseed[- ]0\d\d\b|this session", re.I)


@pytest.mark.parametrize("doc", DOC_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_nothing_points_outside_the_repository(doc):
    hits = [f"{i}: {line.strip()}" for i, line in enumerate(doc.read_text().splitlines(), 1)
            if OUTSIDE.search(line)]
    assert not hits, f"{doc.relative_to(REPO)}:\n" + "\n".join(hits)
