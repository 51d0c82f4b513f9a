"""OUTDIR/manifest.jsonl: one appended record per finished or failed job (docs/batch.md, "Resuming").

Only the run's own process appends (workers return results to it), a line at a time, flushed and fsynced, so a
crash can cut at most the last line, which reading skips and the next append removes."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .digests import file_digest
from .jobs import BatchError

MANIFEST_NAME = "manifest.jsonl"
MAX_MANIFEST_BYTES = 512 * 1024 * 1024
MAX_RECORD_CHARS = 64 * 1024


@dataclass(frozen=True)
class Record:
    """What one job's run left: its output name, input and settings digests, outcome and costs."""

    out: str
    inputs: dict[str, str]  # input name ("bundle", "audio", "motion") -> sha256 of the file
    settings: str  # Job.settings_digest()
    status: str  # "ok" or "failed"
    output: str | None = None  # sha256 of the written file (ok only)
    reason: str = ""  # one line (failed only)
    seconds: float = 0.0  # wall seconds the job took in its worker
    video_s: float = 0.0  # seconds of video it made
    attempts: int = 1
    segments: int = 1  # files the frames were rendered into, then joined
    extra: dict = field(default_factory=dict)  # fields a later version adds, kept when read back


class Manifest:
    """The records of an output folder: read once, appended as jobs finish; the latest record per `out` counts."""

    def __init__(self, outdir: str | os.PathLike) -> None:
        self.path = Path(outdir) / MANIFEST_NAME
        self.latest: dict[str, Record] = {}
        self._complete_bytes = 0
        if self.path.exists():
            self._read()

    def _read(self) -> None:
        size = self.path.stat().st_size
        if size > MAX_MANIFEST_BYTES:
            raise BatchError(f"{self.path}: {size} bytes, more than a manifest may hold ({MAX_MANIFEST_BYTES}); "
                             "start a new output folder")
        data = self.path.read_bytes()
        lines = data.split(b"\n")
        offset = 0
        for number, raw in enumerate(lines, 1):
            last = number == len(lines)
            if last and raw:  # no newline after it: a cut last line, dropped (and cut off before the next append)
                break
            offset += len(raw) + (0 if last else 1)
            if not raw.strip():
                continue
            self._add(raw, number)
        self._complete_bytes = offset

    def _add(self, raw: bytes, number: int) -> None:
        try:
            if len(raw) > MAX_RECORD_CHARS:
                raise ValueError(f"{len(raw)} bytes, more than {MAX_RECORD_CHARS}")
            fields = json.loads(raw)
            known = {name: fields.pop(name) for name in list(fields) if name in Record.__dataclass_fields__}
            record = Record(**known, extra=fields)
            if not isinstance(record.out, str) or not isinstance(record.inputs, dict):
                raise ValueError("out or inputs of the wrong type")
        except (ValueError, TypeError, AttributeError) as exc:
            raise BatchError(f"{self.path}: line {number} is not a batch record ({str(exc).splitlines()[0]}); "
                             "move the file aside to start afresh") from None
        self.latest[record.out] = record

    def append(self, record: Record) -> None:
        """Add one record durably (a cut last line left by a crash is removed first)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "ab") as handle:
            if handle.tell() != self._complete_bytes:
                handle.truncate(self._complete_bytes)
            fields = asdict(record)
            fields.update(fields.pop("extra"))
            line = json.dumps(fields, sort_keys=True).encode() + b"\n"
            handle.write(line)
            handle.flush()
            os.fsync(handle.fileno())
            self._complete_bytes += len(line)
        self.latest[record.out] = record

    def done(self, out: str, inputs: dict[str, str], settings: str, outdir: Path) -> bool:
        """Whether `out` was made from these inputs and settings and is still on disk as recorded."""
        record = self.latest.get(out)
        if record is None or record.status != "ok" or record.inputs != inputs or record.settings != settings:
            return False
        target = outdir / out
        return target.is_file() and file_digest(target) == record.output
