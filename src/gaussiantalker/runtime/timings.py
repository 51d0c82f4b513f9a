"""Per-stage wall times shared by a head's stages (driver, frame renderer, compositor): stage name -> the seconds of
recent calls, bounded so a long-running head's bookkeeping does not grow with the frames it has made."""

from __future__ import annotations

from collections import defaultdict

# At most this many recent calls per stage are kept (then trimmed to the newest half).
MAX_TIMINGS_PER_STAGE = 10_000


class Timings(defaultdict):
    """{stage: [seconds, ...]} (a defaultdict(list), as apps and benches read it) with a bounded `record`."""

    def __init__(self) -> None:
        super().__init__(list)

    def record(self, stage: str, seconds: float) -> None:
        """Append a stage timing; past MAX_TIMINGS_PER_STAGE values only the newest half of that many are kept."""
        values = self[stage]
        values.append(seconds)
        if len(values) > MAX_TIMINGS_PER_STAGE:
            del values[: len(values) - MAX_TIMINGS_PER_STAGE // 2]


__all__ = ["MAX_TIMINGS_PER_STAGE", "Timings"]
