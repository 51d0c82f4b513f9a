"""Progress bars: in place on a terminal, whole lines at most every few seconds in a log."""

from __future__ import annotations

import io

from gaussiantalker.sdk import progress
from gaussiantalker.sdk.progress import progress_bar


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_gets_a_few_whole_lines_not_one_redraw_per_step():
    log = io.StringIO()
    for _ in progress_bar(range(5000), file=log, desc="steps"):
        pass
    text = log.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert 1 <= len(lines) <= 3, lines  # the start, perhaps one interval, the final state
    assert lines[-1].startswith("steps: 100%") and "5000/5000" in lines[-1]


def test_a_log_is_not_flooded_by_postfix_updates():
    """Training loops set the loss as a postfix every step; in a log that waits for the next interval."""
    log = io.StringIO()
    with progress_bar(total=500, file=log, desc="train") as bar:
        for step in range(500):
            bar.update(1)
            bar.set_postfix(loss=f"{1 / (step + 1):.4g}")
            bar.set_description("train")
    lines = log.getvalue().splitlines()
    assert 1 <= len(lines) <= 3, lines
    assert "500/500" in lines[-1] and "loss=0.002" in lines[-1]


def test_a_log_gets_a_line_per_interval(monkeypatch):
    monkeypatch.setattr(progress, "LOG_INTERVAL_S", 0.0)
    log = io.StringIO()
    for _ in progress_bar(range(20), file=log, miniters=1):
        pass
    assert len(log.getvalue().splitlines()) >= 20


def test_a_terminal_gets_redraws_in_place():
    terminal = _Terminal()
    for _ in progress_bar(range(50), file=terminal, mininterval=0, miniters=1):
        pass
    assert terminal.getvalue().count("\r") >= 50


def test_disabled_bar_prints_nothing():
    log = io.StringIO()
    for _ in progress_bar(range(10), file=log, disable=True):
        pass
    assert log.getvalue() == ""
