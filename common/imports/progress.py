"""A progress bar for long loops in a terminal (and plain lines in a log).

One helper for every command that walks many items (imports, exports). On a terminal it redraws
one line ``[#####.....]  12/100  name  3.2 s``; when the stream is not a terminal (a log file, a
pipe, a test) it prints a line per item, so a log shows what was done and when.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressBar:
    """Progress of ``total`` items on ``stream`` (standard error by default).

    Parameters
    ----------
    total : int
        Number of items (>= 0).
    label : str
        Word shown before the bar, e.g. ``"import images"``.
    stream : text stream, optional
        Where to draw (default ``sys.stderr``).
    width : int
        Characters of the bar itself.

    Examples
    --------
    >>> import io
    >>> bar = ProgressBar(2, "demo", stream=io.StringIO())
    >>> bar.update(1, "a.png"); bar.update(2, "b.png"); bar.close()
    """

    def __init__(self, total: int, label: str = "", *, stream: TextIO | None = None, width: int = 30):
        if total < 0:
            raise ValueError(f"total must be >= 0, got {total}")
        self.total, self.label, self.width = int(total), label, int(width)
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = time.monotonic()
        self._drawn = False

    def update(self, done: int, text: str = "") -> None:
        """Show ``done`` of ``total`` items finished, the last one named ``text``."""
        frac = done / self.total if self.total else 1.0
        elapsed = time.monotonic() - self.t0
        n = len(str(self.total))
        if self.tty:
            fill = int(round(frac * self.width))
            line = (f"\r{self.label} [{'#' * fill}{'.' * (self.width - fill)}] {done:>{n}}/{self.total} "
                    f"{text[:40]:<40} {elapsed:6.1f} s")
            self.stream.write(line)
            self._drawn = True
        else:
            self.stream.write(f"[{frac * 100:5.1f}%] {self.label} {done:>{n}}/{self.total} {text} {elapsed:.1f} s\n")
        self.stream.flush()

    def close(self) -> None:
        """End the bar's line (on a terminal)."""
        if self.tty and self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
