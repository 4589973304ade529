"""Progress and live status for every ``capsheet`` command: a terminal gets tqdm's bar (or one
line rewritten in place), a pipe or a log file gets plain lines now and then, ``-q`` gets nothing.

tqdm writes a carriage-return update many times a second; into a file that is hundreds of glued
updates. Here the decision is made once per stream, from ``stream.isatty()``:

* `Progress` — counted work (``n`` of ``total`` trials, snapshots, chunks): on a terminal a tqdm
  bar; otherwise a line ``desc: n/total unit (p %), elapsed, ~left`` at most every ``every_s``
  seconds and one final line; nothing when ``quiet``.
* `LiveLine` — a status that changes (the demo's rate and error, calibration's pose): on a
  terminal one line rewritten with ``\\r`` (at most every ``tty_every_s``); otherwise a plain
  line at most every ``every_s`` — or at once when its ``key`` changes (a new pose to hold).

Both take the clock as an argument (``clock``, default `time.monotonic`), so tests drive them on
a simulated clock with exact counts.

>>> import io
>>> t = [0.0]
>>> out = io.StringIO()
>>> with Progress(4, "noise study", "trial", stream=out, every_s=10, clock=lambda: t[0]) as bar:
...     for _ in range(4):
...         t[0] += 6.0
...         bar.update()
>>> print(out.getvalue(), end="")
noise study: 2/4 trial (50 %), 12 s, ~12 s left
noise study: 4/4 trial (100 %), done in 24 s
"""

from __future__ import annotations

import sys
import time
from typing import Callable, Hashable, TextIO

__all__ = ["Progress", "LiveLine", "is_terminal"]

#: a pipe or a log gets a progress line at most this often, seconds
PLAIN_EVERY_S = 10.0


def is_terminal(stream) -> bool:
    """Whether ``stream`` is an interactive terminal (False for pipes, files, closed streams)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def _seconds(s: float) -> str:
    s = max(0.0, float(s))
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


class Progress:
    """Counted progress: tqdm on a terminal, plain periodic lines elsewhere, nothing if quiet.

    Parameters
    ----------
    total : int or None
        Units of work expected (None: unknown; the lines then give the count only).
    desc, unit : str
        What is counted, e.g. ``"estimate"``, ``"snapshot"``.
    quiet : bool
        Show nothing.
    stream : text stream, optional
        Where to write (default ``sys.stderr``).
    every_s : float
        Plain lines at most this often, seconds (`PLAIN_EVERY_S`).
    clock : callable
        Monotonic seconds (default `time.monotonic`).
    tty : bool, optional
        Override the terminal test (default ``stream.isatty()``).
    """

    def __init__(self, total: int | None, desc: str, unit: str = "it", *, quiet: bool = False,
                 stream: TextIO | None = None, every_s: float = PLAIN_EVERY_S,
                 clock: Callable[[], float] = time.monotonic, tty: bool | None = None) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.total, self.desc, self.unit = total, desc, unit
        self.quiet, self.every_s, self.clock = quiet, float(every_s), clock
        self.tty = is_terminal(self.stream) if tty is None else bool(tty)
        self.n = 0
        self.lines = 0  #: plain lines written (not counting tqdm's redraws)
        self._t0 = clock()
        self._last = self._t0
        self._bar = None
        self._closed = False
        if not quiet and self.tty:
            from tqdm import tqdm
            self._bar = tqdm(total=total, desc=desc, unit=unit, file=self.stream,
                             dynamic_ncols=True)

    def update(self, n: int = 1) -> None:
        """``n`` more units done."""
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        elif not self.quiet:
            now = self.clock()
            if now - self._last >= self.every_s and (self.total is None or self.n < self.total):
                self._line(now)

    def _line(self, now: float, final: bool = False) -> None:
        el = now - self._t0
        if self.total:
            pct = 100.0 * self.n / self.total
            text = f"{self.desc}: {self.n}/{self.total} {self.unit} ({pct:.0f} %), "
            if final:
                text += f"done in {_seconds(el)}"
            else:
                left = el * (self.total - self.n) / self.n if self.n else float("nan")
                text += f"{_seconds(el)}" + (f", ~{_seconds(left)} left" if self.n else "")
        else:
            text = f"{self.desc}: {self.n} {self.unit}, " + (f"done in {_seconds(el)}" if final
                                                            else _seconds(el))
        print(text, file=self.stream, flush=True)
        self.lines += 1
        self._last = now

    def write(self, text: str) -> None:
        """A message line that does not break the bar (tqdm.write on a terminal)."""
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def close(self) -> None:
        """End: the bar closes; a pipe or log gets the final line (if anything was counted)."""
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
        elif not self.quiet and self.n:
            self._line(self.clock(), final=True)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LiveLine:
    """A live status line: rewritten in place on a terminal, plain lines now and then elsewhere.

    ``due()`` says whether a `show` would write now (build an expensive text only then);
    ``show(text, key)`` writes it if due — or at once when ``key`` differs from the last shown;
    ``end()`` finishes a terminal's open line (before other output).

    Parameters
    ----------
    stream : text stream, optional
        Default ``sys.stderr``.
    quiet : bool
        Show nothing.
    tty_every_s, every_s : float
        Minimum seconds between updates on a terminal and elsewhere.
    clock, tty
        As in `Progress`.
    """

    def __init__(self, stream: TextIO | None = None, *, quiet: bool = False,
                 tty_every_s: float = 0.25, every_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, tty: bool | None = None) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.quiet, self.clock = quiet, clock
        self.tty = is_terminal(self.stream) if tty is None else bool(tty)
        self.period = float(tty_every_s if self.tty else every_s)
        self.lines = 0
        self._last: float | None = None
        self._key: Hashable = object()
        self._open = False

    def due(self, key: Hashable = None) -> bool:
        if self.quiet:
            return False
        return (self._last is None or key != self._key
                or self.clock() - self._last >= self.period)

    def show(self, text: str, key: Hashable = None) -> bool:
        """Write ``text`` if due (see `due`); returns whether it was written."""
        if not self.due(key):
            return False
        if self.tty:
            self.stream.write("\r" + text + "\x1b[K")
            self._open = True
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
        self.lines += 1
        self._last, self._key = self.clock(), key
        return True

    def end(self) -> None:
        """End a terminal's open line (so the next output starts on its own line)."""
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False
