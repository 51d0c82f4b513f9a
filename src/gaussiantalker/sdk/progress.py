"""Progress bars that suit both a terminal and a log file.

On a terminal a tqdm bar redraws in place. Into a log (stderr not a terminal: CI, `nohup`, a service) tqdm would
write one carriage-returned redraw per step, hundreds of kilobytes for a demo build; there the bar prints a whole
line at most every `LOG_INTERVAL_S` seconds, plus its final state. tqdm has no line mode of its own, hence the
small writer below.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import IO, Any

from tqdm import tqdm

LOG_INTERVAL_S = 10.0  # seconds between two lines of a bar written into a log


class _LineWriter:
    """File-like wrapper turning tqdm's in-place redraws into whole lines (blank redraws dropped)."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = text.replace("\r", "").strip()
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


class _LogBar(tqdm):
    """A bar whose postfix and description changes wait for the next interval instead of forcing a line each."""

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kwargs: Any) -> None:
        super().set_postfix(ordered_dict, refresh=False, **kwargs)

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        super().set_postfix_str(s, refresh=False)

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        super().set_description(desc, refresh=False)


def progress_bar(iterable: Iterable | None = None, *, file: IO[str] | None = None, **kwargs: Any) -> tqdm:
    """A tqdm bar on `file` (default stderr): in place on a terminal, a line every few seconds in a log."""
    stream = sys.stderr if file is None else file
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return tqdm(iterable, file=stream, **kwargs)
    kwargs.setdefault("mininterval", LOG_INTERVAL_S)
    kwargs.setdefault("ascii", True)  # a log viewer may not be UTF-8
    return _LogBar(iterable, file=_LineWriter(stream), dynamic_ncols=False, ncols=100, **kwargs)
