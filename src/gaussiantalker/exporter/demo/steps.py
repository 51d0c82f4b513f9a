"""How long the demo speaker's trainings run, as step counts (docs/demo-speaker.md, "Identical builds").

A training that stops on the wall clock makes a different speaker on a faster or busier machine; one that stops
after a fixed number of steps makes the same one everywhere. The former time budgets (`train_seconds`,
`inpaint_seconds` and their command-line options) still work: each is read as STEPS_PER_SECOND steps per second,
and says so once.
"""

from __future__ import annotations

import math
import warnings

# What a second of the former time budgets bought on the 2 cores the demo speaker was tuned on, for both trainings
# (docs/demo-speaker.md, "Identical builds").
STEPS_PER_SECOND = 10
INPAINT_STEPS = 600  # the demo speaker's inpainting generator F: its training steps (the former 60 s default)

_told: set[str] = set()


def steps_for_seconds(seconds: float, cap: int | None = None) -> int:
    """The step count a former time budget maps to: `seconds` x STEPS_PER_SECOND, rounded, at most `cap`; 0 is 0
    (no training) and infinity (no budget) is `cap`. ValueError for a negative or NaN budget, or infinity with no
    cap."""
    if not seconds >= 0:
        raise ValueError(f"a training time budget must be >= 0 seconds, got {seconds!r}")
    if math.isinf(seconds):
        if cap is None:
            raise ValueError("an unlimited time budget has no step count here: give the steps instead")
        return cap
    steps = round(seconds * STEPS_PER_SECOND)
    return steps if cap is None else min(steps, cap)


def training_steps(steps: int | None, seconds: float | None, default: int, *, names: tuple[str, str],
                   cap: int | None = None) -> int:
    """The steps a training runs: `steps` if given, else the former budget `seconds` mapped by steps_for_seconds
    (with a FutureWarning, once per process and name, unless it maps exactly: 0 or infinity), else `default`.
    `names`: (the steps keyword, the seconds keyword), for the messages."""
    steps_name, seconds_name = names
    if steps is not None and seconds is not None:
        raise ValueError(f"give {steps_name} or {seconds_name} (its former time budget), not both")
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ValueError(f"{steps_name} must be a whole number >= 0, got {steps!r}")
        return steps
    if seconds is None:
        return default
    mapped = steps_for_seconds(seconds, cap)
    if 0 < seconds < math.inf and seconds_name not in _told:
        _told.add(seconds_name)
        warnings.warn(f"{seconds_name}={seconds:g} is read as {steps_name}={mapped} ({STEPS_PER_SECOND} steps per "
                      f"second; training stops on a step count, so two builds are identical): pass {steps_name}",
                      FutureWarning, stacklevel=3)
    return mapped


__all__ = ["INPAINT_STEPS", "STEPS_PER_SECOND", "steps_for_seconds", "training_steps"]
