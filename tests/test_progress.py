"""pipeline.progress: what a user sees while long work runs (a bar on a terminal, a plain
line at least every few seconds elsewhere, nothing with quiet), and the build printing each
stage's line as the stage finishes."""

from __future__ import annotations

import io
import re
import time

import pytest

from pipeline import progress as prog


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_plain_lines_come_at_least_every_period_even_during_one_long_item():
    out = io.StringIO()
    t0 = time.monotonic()

    def slow():
        yield 1
        time.sleep(1.3)  # one item far longer than the period: the ticker still prints
        yield 2

    assert list(prog.progress(slow(), length=2, label="register", unit="pairs", stream=out, every_s=0.3)) == [1, 2]
    lines = out.getvalue().splitlines()
    assert time.monotonic() - t0 >= 1.3
    assert len(lines) >= 3, lines
    assert re.fullmatch(r"register: [01]/2 pairs, \d+ s", lines[0])
    assert re.fullmatch(r"register: 2/2 pairs, \d+ s \(done\)", lines[-1])
    assert "\r" not in out.getvalue()


def test_short_work_prints_nothing_off_a_terminal_and_quiet_prints_nothing():
    out = io.StringIO()
    assert list(prog.progress(range(5), label="ingest", stream=out, every_s=5.0)) == list(range(5))
    assert out.getvalue() == ""
    tty = FakeTTY()
    assert list(prog.progress(range(5), label="ingest", stream=tty, quiet=True)) == list(range(5))
    assert tty.getvalue() == ""


def test_terminal_gets_a_bar_redrawn_in_place_and_ended_by_a_newline():
    tty = FakeTTY()
    assert list(prog.progress(range(4), label="render", unit="batches", stream=tty)) == [0, 1, 2, 3]
    text = tty.getvalue()
    assert text.startswith("\rrender [")
    assert text.endswith("\n")
    assert "4/4 batches 100 %" in text.rsplit("\r", 1)[1]


def test_counter_advances_from_callbacks():
    out = io.StringIO()
    with prog.counter(3, label="track", unit="frames", stream=out, every_s=0.2) as c:
        for _ in range(3):
            time.sleep(0.15)
            c.advance()
    lines = out.getvalue().splitlines()
    assert lines and lines[-1].startswith("track: 3/3 frames") and lines[-1].endswith("(done)")


def test_activity_prints_only_when_nothing_else_did():
    out = io.StringIO()
    with prog.activity("optimize", stream=out, every_s=0.3):
        time.sleep(1.2)
    lines = out.getvalue().splitlines()
    assert lines and all(re.fullmatch(r"optimize: working, \d+ s", x) for x in lines)
    busy = io.StringIO()
    with prog.activity("render", stream=busy, every_s=0.6):
        for _ in range(8):  # someone else prints every 0.15 s: the activity keeps still
            prog.note_output()
            time.sleep(0.15)
    assert busy.getvalue() == ""
    quiet = io.StringIO()
    with prog.activity("publish", stream=quiet, every_s=0.1, quiet=True):
        time.sleep(0.3)
    assert quiet.getvalue() == ""


def test_an_error_inside_stops_the_ticker_without_a_closing_line():
    out = io.StringIO()
    with pytest.raises(ValueError):
        for i in prog.progress(range(3), label="x", stream=out, every_s=0.05):
            time.sleep(0.1)
            if i == 1:
                raise ValueError("boom")
    n = len(out.getvalue())
    time.sleep(0.2)
    assert len(out.getvalue()) == n  # nothing printed after the loop ended
    assert "(done)" not in out.getvalue()


# --- the build's stage lines, as each stage finishes ----------------------------------------


def _fake_stages(monkeypatch, events: list, fail: str | None = None) -> None:
    """Replace the build's stages by recorders (``fail``: that stage raises JobFailed)."""
    from dataclasses import replace

    from pipeline.stages import build
    from pipeline.errors import JobFailed

    sections = {"ingest": {"ingest": {"frames_accepted": 8, "frames_total": 8}},
                "register": {"registration": {"accepted": 5, "candidates": 6, "pairs_per_s": 50.0}}}
    for name in ("ingest", "register", "optimize"):
        def fn(ws, params, name=name):
            events.append(("start", name))
            if name == fail:
                raise JobFailed(f"{name} failed on purpose")
            return sections.get(name, {})
        monkeypatch.setitem(build.STAGES, name, replace(build.STAGES[name], run=fn, after=None))


def test_run_build_reports_each_stage_before_the_next_starts(small_log, tmp_path, monkeypatch):
    from pipeline.stages.build import run_build
    from pipeline.config import load_config

    events: list = []
    _fake_stages(monkeypatch, events)
    cfg = load_config(None)
    cfg["build"]["stages"] = ["ingest", "register", "optimize"]
    report = run_build([small_log], tmp_path / "w", cfg, quiet=True,
                       on_stage=lambda name, rep: events.append(("done", name, dict(rep["stages"]))))
    assert [e[:2] for e in events] == [("start", "ingest"), ("done", "ingest"), ("start", "register"),
                                       ("done", "register"), ("start", "optimize"), ("done", "optimize")]
    assert list(events[1][2]) == ["ingest"]  # the report so far, this stage in it
    assert list(report["stages"]) == ["ingest", "register", "optimize"]
    # a rerun skips every stage and still reports each
    events.clear()
    run_build([small_log], tmp_path / "w", cfg, quiet=True, on_stage=lambda name, rep: events.append(name))
    assert events == ["ingest", "register", "optimize"]


def test_build_prints_a_stage_line_before_a_later_stage_fails(small_log, tmp_path, monkeypatch):
    from click.testing import CliRunner

    from pipeline.cli import cli

    events: list = []
    _fake_stages(monkeypatch, events, fail="register")
    cfg = tmp_path / "c.toml"
    cfg.write_text('[build]\nstages = ["ingest", "register", "optimize"]\n')
    r = CliRunner().invoke(cli, ["build", str(small_log), "-w", str(tmp_path / "w"), "--config", str(cfg)])
    assert r.exit_code == 1, r.output
    out = r.output
    assert "ingest: done in" in out and "8 of 8 frames accepted" in out
    assert out.index("ingest: done in") < out.index("register failed on purpose")


def test_nested_activities_speak_once():
    out = io.StringIO()
    with prog.activity("build", stream=out, every_s=0.3):
        with prog.activity("register", stream=out, every_s=0.3):
            time.sleep(1.0)
    lines = out.getvalue().splitlines()
    assert lines and all(x.startswith("register: working") for x in lines)


def test_activity_keeps_still_while_a_progress_counter_speaks():
    out = io.StringIO()
    with prog.activity("simulate floor", stream=out, every_s=0.3):
        for _ in prog.progress(range(6), label="simulate floor", unit="frames", stream=out, every_s=0.3):
            time.sleep(0.25)
    lines = out.getvalue().splitlines()
    assert lines and not [x for x in lines if "working" in x], lines


def test_a_counter_starting_after_a_silence_speaks_at_once():
    """The line-every-period promise holds across pieces of work: a counter that starts when
    nothing was printed for a while prints its first line when the period is up, not a whole
    period after its own start."""

    class Timed(io.StringIO):
        stamps: list = []

        def write(self, text):
            self.stamps.append(time.monotonic())
            return super().write(text)

    out = Timed()
    t0 = time.monotonic()
    with prog.activity("build", stream=out, every_s=1.0):
        time.sleep(1.9)  # the activity speaks at 1 s; the counter starts 0.9 s later
        for _ in prog.progress(range(4), label="register", stream=out, every_s=1.0):
            time.sleep(0.4)
    times = [t0] + out.stamps
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("build: working") and lines[1].startswith("register: ")
    # a whole period of the counter's own after its start would make a 1.9 s gap
    assert max(b - a for a, b in zip(times, times[1:])) < 1.6, lines


def test_a_stage_starting_inside_a_command_keeps_the_commands_cadence():
    """A nested activity speaks when the command has been silent for a period, not a whole
    period after the nested one started."""
    out = io.StringIO()
    t0 = time.monotonic()
    with prog.activity("build", stream=out, every_s=1.0):
        time.sleep(0.6)
        with prog.activity("ingest", stream=out, every_s=1.0):
            while not out.getvalue() and time.monotonic() - t0 < 3.0:
                time.sleep(0.05)
            first = time.monotonic() - t0
    assert out.getvalue().startswith("ingest: working")
    assert first < 1.5  # not 0.6 + 1.0
