"""Read and check a whole job list (JSON Lines or CSV, docs/batch.md) before anything renders: every bad line is
named with its line number in one BatchError, so a list of thousands is fixed in one pass, not one crash at a time.

The file is a user's input: its size, its line count and each line's length are bounded before it is parsed."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path, PurePosixPath

from gaussiantalker.sdk.json_bounds import no_constant
from gaussiantalker.sdk.video import check_fps
from gaussiantalker.sdk.video_formats import CODECS, CONTAINERS

from .jobs import BatchError, Job

MAX_JOB_FILE_BYTES = 64 * 1024 * 1024
MAX_JOBS = 100_000
MAX_LINE_CHARS = 16 * 1024
MAX_SIDE = 8192  # the largest resolution side a job may ask for
MAX_NAME_CHARS = 255  # one component of `out` (the usual file-system limit)
MAX_LISTED = 100  # problems spelled out in one error; the rest are counted
FIELDS = ("bundle", "audio", "motion", "out", "resolution", "composite", "camera", "codec", "crf", "fps")
MAX_PITCH = 89.0  # degrees: the orbit's pitch stays short of looking straight down or up
# Single-file containers: an image sequence is a folder of files, which the manifest's one output digest and the
# one atomic rename do not describe.
SUFFIXES = tuple(ext for spec in CONTAINERS.values() if not spec.sequence for ext in spec.extensions)
_TRUE, _FALSE = ("true", "1", "yes"), ("false", "0", "no")


def read_jobs(path: str | os.PathLike) -> list[Job]:
    """The checked jobs of a `.jsonl` / `.ndjson` / `.csv` job list (relative inputs resolve against its folder);
    BatchError listing every bad line."""
    path = Path(path)
    rows, problems = _rows(path)
    jobs, seen = [], {}
    for line, row in rows:
        try:
            job = job_from_fields(row, line, path.parent)
        except ValueError as exc:
            problems.append(f"line {line}: {exc}")
            continue
        if job.out in seen:
            problems.append(f"line {line}: out {job.out!r} is already written by line {seen[job.out]}")
            continue
        seen[job.out] = line
        jobs.append(job)
    if not jobs and not problems:
        problems.append("no jobs in the file")
    if problems:
        raise BatchError(listing(path, sorted(problems, key=_line_number)))
    return jobs


def _line_number(problem: str) -> int:
    """The line a 'line N: ...' problem names (0 for a problem of the whole file)."""
    words = problem.split(":", 1)[0].split()
    return int(words[1]) if len(words) == 2 and words[0] == "line" and words[1].isdigit() else 0


def listing(path: Path, problems: list[str]) -> str:
    """One error text for many problems of one file: counted, the first MAX_LISTED spelled out."""
    shown = problems[:MAX_LISTED]
    more = f"\n... and {len(problems) - MAX_LISTED} more" if len(problems) > MAX_LISTED else ""
    return f"{path}: {len(problems)} bad job line(s):\n" + "\n".join(shown) + more


def _text(path: Path) -> str:
    """The file's text, its size and encoding checked first."""
    try:
        size = path.stat().st_size
        if not path.is_file():
            raise BatchError(f"{path}: not a file")
        if size > MAX_JOB_FILE_BYTES:
            raise BatchError(f"{path}: {size} bytes, more than a job list may hold ({MAX_JOB_FILE_BYTES})")
        data = path.read_bytes()[:MAX_JOB_FILE_BYTES]
    except OSError as exc:
        raise BatchError(f"{path}: cannot read the job list ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise BatchError(f"{path}: not UTF-8 text (byte {exc.start})") from None


def _rows(path: Path) -> tuple[list[tuple[int, dict]], list[str]]:
    """(line number, fields) of each job line, and the problems found reading them."""
    suffix = path.suffix.lower()
    if suffix not in (".jsonl", ".ndjson", ".csv"):
        raise BatchError(f"{path}: a job list is .jsonl, .ndjson or .csv, not {suffix or 'a file without suffix'!r}")
    lines = _text(path).splitlines()
    if len(lines) > MAX_JOBS + 1:
        raise BatchError(f"{path}: {len(lines)} lines, more than a job list may hold ({MAX_JOBS} jobs)")
    long = [f"line {n}: {len(text)} characters, more than {MAX_LINE_CHARS}"
            for n, text in enumerate(lines, 1) if len(text) > MAX_LINE_CHARS]
    if long:
        raise BatchError(listing(path, long))
    return _csv_rows(lines) if suffix == ".csv" else _json_rows(lines)


def _json_rows(lines: list[str]) -> tuple[list[tuple[int, dict]], list[str]]:
    rows, problems = [], []
    for number, text in enumerate(lines, 1):
        if not text.strip():
            continue
        try:
            row = json.loads(text, parse_constant=no_constant)
        except (ValueError, RecursionError) as exc:
            problems.append(f"line {number}: not JSON ({str(exc).splitlines()[0]})")
            continue
        if not isinstance(row, dict):
            problems.append(f"line {number}: a job is a JSON object, got {type(row).__name__}")
            continue
        rows.append((number, row))
    return rows, problems


def _csv_rows(lines: list[str]) -> tuple[list[tuple[int, dict]], list[str]]:
    reader = csv.reader(io.StringIO("\n".join(lines)), strict=True)
    rows, problems = [], []
    try:
        header = next(reader, None)
        if header is None:
            return rows, problems
        names = [name.strip() for name in header]
        unknown = [name for name in names if name not in FIELDS]
        if unknown or len(set(names)) != len(names):
            return rows, [f"line 1: the header's columns must be distinct names among {', '.join(FIELDS)}, got "
                          f"{', '.join(map(repr, names))}"]
        start = reader.line_num + 1
        for cells in reader:
            if any(cell.strip() for cell in cells):
                if len(cells) != len(names):
                    problems.append(f"line {start}: {len(cells)} cells, the header has {len(names)}")
                else:
                    rows.append((start, {k: v.strip() for k, v in zip(names, cells, strict=True) if v.strip()}))
            start = reader.line_num + 1
    except csv.Error as exc:
        problems.append(f"line {reader.line_num}: not CSV ({exc})")
    return rows, problems


def job_from_fields(row: dict, line: int, base: Path) -> Job:
    """One job from its fields (JSON values, or CSV text); ValueError naming every bad field."""
    problems = [f"unknown field {name!r} (known: {', '.join(FIELDS)})" for name in row if name not in FIELDS]
    found: dict = {}
    for name, check in (("bundle", _input), ("audio", _input), ("motion", _input), ("out", _out),
                        ("resolution", _resolution), ("composite", _composite), ("camera", _camera),
                        ("codec", _codec), ("crf", _crf), ("fps", _fps)):
        if row.get(name) is None:
            continue
        try:
            found[name] = check(row[name], base) if check is _input else check(row[name])
        except ValueError as exc:
            problems.append(f"{name}: {exc}")
    for name in ("bundle", "out"):
        if row.get(name) is None:
            problems.append(f"{name} is missing")
    if row.get("audio") is None and row.get("motion") is None:
        problems.append("a job needs audio or motion (or both: the motion plays with the audio muxed in)")
    problems += _coherent(found)
    if problems:
        raise ValueError("; ".join(problems))
    if "camera" in found and found.get("composite") is None:
        found["composite"] = False  # a view from elsewhere is of the bare head
    return Job(line=line, **found)


def _coherent(found: dict) -> list[str]:
    """Problems between fields: a camera on a composited frame, a codec its container does not hold, a crf its
    codec has no scale for."""
    problems = []
    if found.get("camera") is not None and found.get("composite") is True:
        problems.append("camera: a composited frame is seen through the reference clip's camera; drop composite "
                        "or set it false")
    container = _container(found["out"]) if "out" in found else None
    codec = found.get("codec") or (container.codecs[0] if container is not None else None)
    if container is not None and codec not in container.codecs:
        problems.append(f"codec: {container.name} holds {', '.join(container.codecs)}, not {codec}")
    if found.get("crf") is not None:
        spec = CODECS.get(codec) if codec is not None else None
        if spec is not None and spec.crf is None:
            problems.append(f"crf: {spec.name} has no crf")
        elif spec is not None and not spec.crf[0] <= found["crf"] <= spec.crf[1]:
            problems.append(f"crf: {spec.name} takes {spec.crf[0]}..{spec.crf[1]}, got {found['crf']}")
    return problems


def _input(value: object, base: Path) -> Path:
    if not isinstance(value, str) or not value or "\0" in value:
        raise ValueError(f"expected a file path, got {_shown(value)}")
    path = (base / value).absolute()
    if not path.is_file():
        raise ValueError(f"{path} is not a file")
    return path


def _out(value: object) -> str:
    if not isinstance(value, str) or not value.strip() or "\0" in value or "\\" in value:
        raise ValueError(f"expected a relative file name such as talk.mp4, got {_shown(value)}")
    out = PurePosixPath(value)
    if out.is_absolute() or ".." in out.parts:
        raise ValueError(f"{value!r} must stay under the output folder (no absolute path, no '..')")
    if any(part.startswith(".") or len(part) > MAX_NAME_CHARS for part in out.parts):
        raise ValueError(f"{value!r}: no hidden names (the batch's partial files are hidden) and at most "
                         f"{MAX_NAME_CHARS} characters a name")
    if out.suffix.lower() not in SUFFIXES:
        raise ValueError(f"{value!r}: the suffix picks the container, one of {', '.join(SUFFIXES)} "
                         "(image sequences are not batch outputs; .mkv holds lossless ffv1)")
    return str(out)


def _resolution(value: object) -> tuple[int, int]:
    if isinstance(value, str):  # CSV: "512" or "512x288"
        parts = value.lower().split("x")
        if not all(part.strip().isdigit() for part in parts) or len(parts) > 2:
            raise ValueError(f"expected N or WxH, got {_shown(value)}")
        value = [int(part) for part in parts] if len(parts) == 2 else int(parts[0])
    if _is_int(value):
        value = [value, value]
    if not isinstance(value, list | tuple) or len(value) != 2 or not all(map(_is_int, value)):
        raise ValueError(f"expected an integer or [width, height], got {_shown(value)}")
    if not all(1 <= side <= MAX_SIDE for side in value):
        raise ValueError(f"sides must be 1..{MAX_SIDE}, got {value[0]}x{value[1]}")
    return int(value[0]), int(value[1])


def _composite(value: object) -> bool:
    if isinstance(value, str) and value.lower() in _TRUE + _FALSE:
        return value.lower() in _TRUE
    if not isinstance(value, bool):
        raise ValueError(f"expected true or false, got {_shown(value)}")
    return value


def _container(out: str):
    """The container an output's suffix picks (`_out` has checked it is one)."""
    suffix = PurePosixPath(out).suffix.lower()
    return next(spec for spec in CONTAINERS.values() if suffix in spec.extensions)


def _camera(value: object) -> tuple[float, float]:
    """{"yaw": deg, "pitch": deg}, [yaw, pitch], or CSV text "yaw pitch" / "yaw;pitch"."""
    if isinstance(value, str):
        parts = value.replace(";", " ").replace(",", " ").split()
        try:
            value = [float(part) for part in parts]
        except ValueError:
            raise ValueError(f"expected 'YAW PITCH' in degrees, got {_shown(value)}") from None
    if isinstance(value, dict):
        unknown = sorted(set(value) - {"yaw", "pitch"})
        if unknown:
            raise ValueError(f"a camera has yaw and pitch (degrees), not {', '.join(map(repr, unknown))}")
        value = [value.get("yaw", 0.0), value.get("pitch", 0.0)]
    if not isinstance(value, list | tuple) or len(value) != 2 or not all(_is_real(v) for v in value):
        raise ValueError(f'expected {{"yaw": degrees, "pitch": degrees}} or [yaw, pitch], got {_shown(value)}')
    yaw, pitch = float(value[0]), float(value[1])
    if not (math.isfinite(yaw) and -180.0 <= yaw <= 180.0 and math.isfinite(pitch) and abs(pitch) <= MAX_PITCH):
        raise ValueError(f"yaw must be -180..180 and pitch -{MAX_PITCH:g}..{MAX_PITCH:g} degrees, got "
                         f"{_shown(value[0])}, {_shown(value[1])}")
    return yaw, pitch


def _codec(value: object) -> str:
    if not isinstance(value, str) or value not in CODECS:
        raise ValueError(f"expected one of {', '.join(CODECS)}, got {_shown(value)}")
    return value


def _crf(value: object) -> int:
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value)
    if not _is_int(value) or not 0 <= value <= 63:
        raise ValueError(f"expected a whole number 0..63, got {_shown(value)}")
    return value


def _fps(value: object) -> float:
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise ValueError(f"expected frames per second, got {_shown(value)}") from None
    try:
        return check_fps(value)
    except ValueError as exc:
        raise ValueError(str(exc).removeprefix("fps ")) from None


def _is_real(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _shown(value: object) -> str:
    """A bad value for a one-line message, cut short."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."

