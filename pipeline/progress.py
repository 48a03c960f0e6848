"""Progress a user sees on stderr while long work runs (no click: algorithm modules use it).

Two shapes, chosen by whether stderr is a terminal:

* a terminal: a bar redrawn in place (``ingest d1 [#######-----]  120/400 frames  30 %  14 s``),
  ended by a newline when the work ends;
* anything else (a log file, a pipe, CI): a plain line at least every :data:`EVERY_S` seconds
  (``ingest d1: 120/400 frames, 14 s``) and one when the work ends (when it took that long),
  so that a log shows the work moving without carriage returns.

``quiet`` prints nothing. :func:`progress` wraps an iterable (:func:`counter`: work advanced
by callbacks); :func:`activity` covers work that has no count (a command, a build stage): it
prints ``optimize: working, 20 s`` only when nothing was printed for :data:`EVERY_S` seconds
and no counter is running. They print from a daemon thread, so a single item that takes a
minute still gives a line every :data:`EVERY_S` seconds.
"""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from typing import IO, Iterable, Iterator, TypeVar

T = TypeVar("T")

# Seconds between two plain progress lines when stderr is not a terminal (and at most this
# long without any line while a progress or activity runs).
EVERY_S = 5.0
# Seconds between two redraws of a terminal bar.
REDRAW_S = 0.2
BAR_WIDTH = 28

_lock = threading.Lock()
_last_output = [0.0]  # time.monotonic() of the last progress output, shared by every reporter
_counters = [0]  # progress counters running (an activity stays silent while one speaks)
_activities: list[tuple[object, float]] = []  # activities running (token, start), innermost last


def _stream(stream: IO[str] | None) -> IO[str]:
    return sys.stderr if stream is None else stream


def _is_tty(stream: IO[str]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _write(stream: IO[str], text: str) -> None:
    with _lock:
        try:
            stream.write(text)
            stream.flush()
        except (ValueError, OSError):  # a closed stream: progress is never worth an error
            pass
        _last_output[0] = time.monotonic()


def note_output() -> None:
    """Tell the reporters that a line was just printed (an activity then waits another
    :data:`EVERY_S` seconds before its next line)."""
    _last_output[0] = time.monotonic()


class _Ticker:
    """A daemon thread calling ``fn()`` every ``period`` seconds until stopped."""

    def __init__(self, fn, period: float):
        self._fn, self._period = fn, period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="mosaicmap-progress")

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            self._fn()

    def __enter__(self) -> "_Ticker":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def _count_text(done: int, length: int | None, unit: str) -> str:
    total = f"/{length}" if length is not None else ""
    return f"{done}{total}" + (f" {unit}" if unit else "")


class Counter:
    """Progress of ``length`` steps of the work ``label``, advanced by :meth:`advance`; a
    context manager (the closing line or newline on exit). See :func:`progress`."""

    def __init__(self, length: int | None, *, label: str = "", quiet: bool = False, unit: str = "",
                 stream: IO[str] | None = None, every_s: float = EVERY_S):
        self.length, self.label, self.quiet, self.unit, self.every_s = length, label, quiet, unit, every_s
        self.out = _stream(stream)
        self.tty = not quiet and _is_tty(self.out)
        self.done = 0
        self._t0 = self._printed_at = time.monotonic()
        self._ticker: _Ticker | None = None

    def _plain(self, final: bool = False) -> None:
        now = time.monotonic()
        # a line when nothing at all was printed for every_s (this counter's lines, or another's
        # before it started); the closing line only after a line on the way: short work prints nothing
        if (final and self._printed_at > self._t0) or (not final and now - _last_output[0] >= self.every_s):
            self._printed_at = now
            head = f"{self.label}: " if self.label else ""
            _write(self.out, f"{head}{_count_text(self.done, self.length, self.unit)}, {now - self._t0:.0f} s"
                             f"{' (done)' if final else ''}\n")

    def _bar(self, final: bool = False) -> None:
        done, length, elapsed = self.done, self.length, time.monotonic() - self._t0
        if length:
            filled = min(BAR_WIDTH, BAR_WIDTH * done // length)
            drawn = (f"[{'#' * filled}{'-' * (BAR_WIDTH - filled)}] {_count_text(done, length, self.unit)} "
                     f"{100 * done // length:3d} %")
        else:
            drawn = _count_text(done, None, self.unit)
        _write(self.out, f"\r{self.label} {drawn}  {elapsed:.0f} s\033[K" + ("\n" if final else ""))

    def _show(self, final: bool = False) -> None:
        (self._bar if self.tty else self._plain)(final)

    def advance(self, n: int = 1) -> None:
        """``n`` more steps done."""
        self.done += n
        if self.tty and time.monotonic() - _last_output[0] >= REDRAW_S:
            self._show()

    def __enter__(self) -> "Counter":
        if self.quiet:
            return self
        _counters[0] += 1
        self._ticker = _Ticker(self._show, REDRAW_S if self.tty else min(self.every_s / 5, 1.0)).__enter__()
        if self.tty:
            self._show()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if self._ticker is None:
            return
        self._ticker.__exit__(exc_type, *exc)
        _counters[0] -= 1
        if exc_type is None or self.tty:
            self._show(final=True)


def counter(length: int | None, *, label: str = "", quiet: bool = False, unit: str = "",
            stream: IO[str] | None = None, every_s: float = EVERY_S) -> Counter:
    """A :class:`Counter` (``with counter(n, label="track") as c: ... c.advance()``): the
    progress of work that is not a loop over an iterable."""
    return Counter(length, label=label, quiet=quiet, unit=unit, stream=stream, every_s=every_s)


def progress(items: Iterable[T], *, length: int | None = None, label: str = "", quiet: bool = False,
             unit: str = "", stream: IO[str] | None = None, every_s: float = EVERY_S) -> Iterator[T]:
    """Iterate over ``items`` showing progress on ``stream`` (default stderr).

    ``length``: the number of items (default ``len(items)`` when it has one); ``label``
    names the work, ``unit`` its items (``"frames"``). A terminal gets a bar; anything else
    a plain line ``label: done/length unit, S s`` at least every ``every_s`` seconds (and
    one at the end if any was printed before). ``quiet``: nothing is printed.
    """
    if quiet:
        yield from items
        return
    if length is None:
        try:
            length = len(items)  # type: ignore[arg-type]
        except TypeError:
            length = None
    with Counter(length, label=label, unit=unit, stream=stream, every_s=every_s) as c:
        for item in items:
            yield item
            c.advance()


@contextmanager
def activity(label: str, *, quiet: bool = False, stream: IO[str] | None = None,
             every_s: float = EVERY_S, since: float | None = None) -> Iterator[None]:
    """Show that the work ``label`` is running: ``label: working, S s`` whenever nothing was
    printed for ``every_s`` seconds (a terminal: redrawn in place, then erased, and never
    over a progress bar). Nested activities (a command, then a stage in it): the innermost
    speaks. ``since``: when the work started (``time.monotonic()``; default now), e.g. when
    the process started importing. ``quiet``: nothing."""
    if quiet:
        yield
        return
    out = _stream(stream)
    tty = _is_tty(out)
    t0 = time.monotonic() if since is None else since
    drawn = [False]
    me = object()

    def tick() -> None:
        now = time.monotonic()
        if _activities[-1][0] is not me or _counters[0]:  # the innermost speaks, and not over a counter
            return
        if tty:
            if now - t0 >= 1.0:
                _write(out, f"\r{label}: working, {now - t0:.0f} s\033[K")
                drawn[0] = True
        # silent for a period, counted from the outermost activity's start (a stage starting
        # 3 s into a command speaks 2 s later, not 5)
        elif now - _last_output[0] >= every_s and now - _activities[0][1] >= every_s:
            _write(out, f"{label}: working, {now - t0:.0f} s\n")

    entry = (me, t0)
    _activities.append(entry)
    try:
        with _Ticker(tick, 1.0 if tty else min(every_s / 5, 1.0)):
            yield
    finally:
        _activities.remove(entry)
        if drawn[0]:
            _write(out, "\r\033[K")
