"""Where a job's output is written while it renders: a hidden partial name beside the final one, renamed onto it
only when complete, so no half file ever stands under a final name (docs/batch.md, "Failures")."""

from __future__ import annotations

import os
from pathlib import Path


def partial_path(target: Path, pid: int | None = None) -> Path:
    """`.NAME.partial-PID.SUFFIX` beside `target`: the same suffix (it picks the container), one per process."""
    return target.with_name(f".{target.name}.partial-{os.getpid() if pid is None else pid}{target.suffix}")


def segment_path(target: Path, index: int) -> Path:
    """`.NAME.segment-0003.SUFFIX` beside `target`: segment `index` of a split job, in the output's container."""
    return target.with_name(f".{target.name}.segment-{index:04d}{target.suffix}")


def remove_partials(target: Path) -> list[Path]:
    """Remove what a job's steps left beside `target`: partial files, segments and the video writer's own staged
    files beside them (`..NAME.partial-*`, `..NAME.segment-*`); returns what was removed."""
    if not target.parent.is_dir():
        return []
    removed = []
    for prefix in (f"{dots}{target.name}.{kind}-" for dots in (".", "..") for kind in ("partial", "segment")):
        for path in target.parent.glob(_escaped(prefix) + "*"):
            if path.is_file():
                path.unlink(missing_ok=True)
                removed.append(path)
    return removed


def _escaped(text: str) -> str:
    """`text` as a literal glob pattern."""
    return "".join(f"[{c}]" if c in "*?[" else c for c in text)
