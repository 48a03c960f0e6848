"""The command line a newcomer meets: one command table in workflow order, help that lists
whole descriptions and shows defaults, --config/--quiet on every command (or its help says
why not), lazy loading, and click only in pipeline/cli/."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from pipeline.cli import COMMANDS, cli
from pipeline.cli.common import NO_CONFIG, NO_QUIET

REPO = Path(__file__).resolve().parent.parent

# The workflow a user follows, in the order `mosaicmap --help` must list it.
WORKFLOW = ["simulate", "import-bag", "import-tiles", "import-geotagged", "ingest", "build", "show", "log", "tag",
            "rollback", "poses", "quicklook", "diff", "export", "verify", "apply-delta", "track", "config", "keys",
            "gc"]


def _leaves(group: click.Group, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], click.Command]]:
    """Every runnable command under ``group``: (path of names, command)."""
    out = []
    ctx = click.Context(group)
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if isinstance(cmd, click.Group):
            out.extend(_leaves(cmd, prefix + (name,)))
        else:
            out.append((prefix + (name,), cmd))
    return out


LEAVES = _leaves(cli)


def test_help_lists_every_command_in_workflow_order_with_whole_descriptions():
    r = CliRunner().invoke(cli, ["--help"], terminal_width=80)
    assert r.exit_code == 0, r.output
    assert [e.name for e in COMMANDS] == WORKFLOW
    listed = [m.group(1) for m in re.finditer(r"^  ([a-z-]+)  +\S", r.output, re.M) if m.group(1) in WORKFLOW]
    assert listed == WORKFLOW
    # click's default cuts a description at the terminal width with "...": never here
    assert "..." not in r.output.split("\n", 1)[1]  # (the usage line ends with ARGS]...)
    flat = " ".join(r.output.split())
    for e in COMMANDS:
        assert e.summary in flat, e.name


def test_table_summaries_are_the_commands_own_first_sentences():
    ctx = click.Context(cli)
    for e in COMMANDS:
        cmd = cli.get_command(ctx, e.name)
        assert cmd is not None and cmd.name == e.name
        assert cmd.get_short_help_str(10_000) == e.summary, e.name


def test_subgroup_help_lists_whole_descriptions():
    r = CliRunner().invoke(cli, ["simulate", "--help"], terminal_width=60)
    assert r.exit_code == 0
    assert "..." not in r.output.split("\n", 1)[1]
    assert "stage-scanned tile grid (microscope) into the folder OUT." in " ".join(r.output.split())


@pytest.mark.parametrize("path,cmd", LEAVES, ids=[" ".join(p) for p, _ in LEAVES])
def test_every_command_takes_config_and_quiet_or_says_why_not(path, cmd):
    opts = {o for p in cmd.params if isinstance(p, click.Option) for o in p.opts}
    help_text = " ".join((cmd.help or "").split())
    for option, sentence in (("--config", NO_CONFIG), ("--quiet", NO_QUIET)):
        # exactly one of: the option, or the sentence saying it does not apply
        assert (option in opts) != (sentence in help_text), (path, option)
    r = CliRunner().invoke(cli, [*path, "--help"], terminal_width=100)
    assert r.exit_code == 0
    flat = " ".join(r.output.split())
    assert ("--config" in opts) == (NO_CONFIG not in flat) and ("--quiet" in opts) == (NO_QUIET not in flat)


def test_which_commands_take_config_and_quiet():
    """Everything that prints progress takes --quiet; everything configured takes --config
    (the table the README gives)."""
    takes = {" ".join(p): {o for q in c.params if isinstance(q, click.Option) for o in q.opts} for p, c in LEAVES}
    quiet = {n for n, opts in takes.items() if "--quiet" in opts and "-q" in opts}
    config = {n for n, opts in takes.items() if "--config" in opts}
    assert quiet == {"simulate floor", "simulate omni", "simulate tiles", "import-bag", "import-tiles",
                     "import-geotagged", "ingest", "build", "diff", "export", "track"}
    assert config == {"simulate floor", "simulate omni", "simulate tiles", "import-bag", "ingest", "build", "diff",
                      "export", "track", "config show"}


def test_simulate_help_shows_the_configured_defaults():
    r = CliRunner().invoke(cli, ["simulate", "floor", "--help"], terminal_width=200)
    assert r.exit_code == 0
    assert "[default: (simulate.floor.area_m = 5x5)]" in r.output
    assert "[default: (simulate.floor.route = lawnmower)]" in r.output
    assert "[default: (simulate.seed = 0)]" in r.output
    r = CliRunner().invoke(cli, ["simulate", "tiles", "--help"], terminal_width=200)
    assert "[default: (simulate.tiles.grid = 5x5)]" in r.output


def test_group_shows_every_default():
    """show_default is on for every command (the group's context settings, inherited)."""
    root = click.Context(cli, **cli.context_settings)
    for path, cmd in LEAVES:
        assert click.Context(cmd, parent=root).show_default is True, path
    r = CliRunner().invoke(cli, ["gc", "--help"], terminal_width=200)
    assert "[default: 7d]" in r.output


def test_help_imports_no_command_module():
    """`mosaicmap --help` reads the table: no command module, no numpy/zarr/icechunk/cv2;
    a command imports its own module only."""
    code = ("import sys\nfrom pipeline.cli import cli\n"
            "try:\n    cli(sys.argv[1:], prog_name='mosaicmap')\nexcept SystemExit:\n    pass\n"
            "print('MODULES', ' '.join(sorted(sys.modules)))\n")
    heavy = {"numpy", "zarr", "icechunk", "cv2", "OpenImageIO", "gtsam", "dask", "matplotlib"}

    def modules(*args: str) -> set[str]:
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=REPO, timeout=120)
        line = next(x for x in r.stdout.splitlines() if x.startswith("MODULES "))
        return set(line.split()[1:])

    top = modules("--help")
    assert not {m for m in top if m.startswith("pipeline.cli.") and m != "pipeline.cli.common"}
    assert not (heavy & top)
    keys = modules("keys", "--help")
    assert "pipeline.cli.keys" in keys
    assert not {"pipeline.cli.export", "pipeline.cli.track", "pipeline.cli.build"} & keys


def test_python_m_pipeline_cli_runs():
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "--version"], capture_output=True, text=True,
                       cwd=REPO, timeout=120)
    assert r.returncode == 0 and "mosaicmap, version" in r.stdout


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_no_module_outside_the_cli_imports_click():
    """click belongs to pipeline/cli/: algorithm modules report progress through
    pipeline.progress, the vehicle side and the map store know nothing of a command line."""
    offenders = []
    for pkg in ("pipeline", "mapstore", "tracker"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            if path.is_relative_to(REPO / "pipeline" / "cli"):
                continue
            if "click" in _imports(path):
                offenders.append(str(path.relative_to(REPO)))
    assert offenders == []
    assert "click" in _imports(REPO / "pipeline" / "cli" / "__init__.py")  # the check sees imports at all


def _pipeline_imports(path: Path) -> set[str]:
    """The ``pipeline.*`` modules ``path`` imports (absolute or relative), by full name."""
    pkg = ".".join(path.relative_to(REPO).with_suffix("").parts[:-1])
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1] + ([base] if base else []))
            names.update([base] + [f"{base}.{a.name}" for a in node.names])
    return {n for n in names if n == "pipeline" or n.startswith("pipeline.")}


def test_no_algorithm_module_imports_a_stage_or_the_cli():
    """The algorithm modules (flat in pipeline/) are the library the stages, the importers and
    the command line are built on: none of them imports pipeline.stages or pipeline.cli (nor
    the importers or the test fixtures)."""
    wings = ("pipeline.stages", "pipeline.cli", "pipeline.importers", "pipeline.testing")
    offenders = {}
    flat = sorted(p for p in (REPO / "pipeline").glob("*.py") if p.name != "__init__.py")
    assert len(flat) > 20 and (REPO / "pipeline" / "stages" / "build.py").is_file()
    for path in flat:
        bad = sorted(n for n in _pipeline_imports(path) if n.startswith(tuple(w + "." for w in wings)) or n in wings)
        if bad:
            offenders[path.name] = bad
    assert offenders == {}
    # the check sees such imports at all: a stage imports the workspace, the CLI a stage
    assert "pipeline.stages.workspace" in _pipeline_imports(REPO / "pipeline" / "stages" / "render.py")
    assert "pipeline.stages.build" in _pipeline_imports(REPO / "pipeline" / "cli" / "build.py")


def test_log_lines_are_plain_unless_verbose():
    """Log lines without time stamp or logger name (warnings marked), unless -v."""
    code = ("import logging, sys\nfrom pipeline.cli.common import setup_logging\n"
            "setup_logging(sys.argv[1] == 'v')\n"
            "logging.getLogger('pipeline.x').info('hello')\nlogging.getLogger('pipeline.x').warning('careful')\n")
    plain = subprocess.run([sys.executable, "-c", code, "plain"], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert plain.stderr == "hello\nwarning: careful\n"
    verbose = subprocess.run([sys.executable, "-c", code, "v"], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ INFO pipeline.x: hello$", verbose.stderr.splitlines()[0])


def test_a_truncated_png_gives_one_line_and_no_libpng_noise(tmp_path):
    """libpng prints `libpng error: ...` on stderr itself when it hits the end of a cut PNG:
    the reader refuses such a file before decoding, with our one line only."""
    code = ("import sys\nimport numpy as np\nfrom pipeline.images import read_grey, write_grey\n"
            "from pipeline.errors import BadInput\n"
            "p = sys.argv[1]\nwrite_grey(p, (np.arange(64 * 80) % 251).reshape(64, 80).astype(np.uint8))\n"
            "assert read_grey(p).shape == (64, 80)\n"
            "open(p + '.extra.png', 'wb').write(open(p, 'rb').read() + b'trailing bytes')\n"
            "assert read_grey(p + '.extra.png').shape == (64, 80)\n"
            "data = open(p, 'rb').read()\nopen(p, 'wb').write(data[: len(data) // 2])\n"
            "try:\n    read_grey(p)\nexcept BadInput as e:\n    print('REFUSED', e)\n")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "cut.png")], capture_output=True, text=True,
                       cwd=REPO, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "REFUSED" in r.stdout and "cut.png: corrupt or truncated image" in r.stdout
    assert "libpng" not in r.stderr and r.stderr == ""


def test_no_icechunk_concurrency_warning_on_a_local_repository(tmp_path):
    """icechunk warns on every local repository that it is unsafe for concurrent commits;
    our commit lock makes it safe, so a command prints no such line (a commit included)."""
    from mapstore.repository import MapRepository

    url = str(tmp_path / "repo")
    MapRepository.create(url)
    env = {k: v for k, v in os.environ.items() if k != "ICECHUNK_LOG"}
    for args in (["log", url], ["tag", url, "main", "first"]):
        r = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], capture_output=True, text=True, cwd=REPO,
                           env=env, timeout=120)
        assert r.returncode == 0, r.stderr
        assert "not safe" not in r.stderr and "WARN" not in r.stderr, r.stderr


def test_a_help_with_an_added_sentence_keeps_its_text_flowing():
    """The "No --config" sentence appended to a help does not break the docstring's dedent."""
    r = CliRunner().invoke(cli, ["verify", "--help"], terminal_width=200)
    assert "every member's name, checksum and size bounds" in r.output
    assert "  " not in r.output.split("Options:")[0].replace("\n  ", "\n").strip().replace("\n\n", "\n")


def test_progress_label_of_a_command_line():
    from pipeline.cli import _argv_label

    assert _argv_label(["simulate", "floor", "out", "--seed", "1"]) == "simulate floor"
    assert _argv_label(["-v", "build", "logs", "--map", "m"]) == "build"
    assert _argv_label(["nonsense"]) == "mosaicmap" and _argv_label([]) == "mosaicmap"
