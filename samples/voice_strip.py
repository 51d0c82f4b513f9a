"""A strip of frames for one sentence: `python samples/voice_strip.py avatar.zip [-o docs/bench/voice/strip.png]`.

Imports a LAM avatar zip (docs/import.md), attaches the built-in voice driver (docs/voice.md), saves its checkpoint
and exports its bundle into a temporary folder (nothing of the avatar is kept), then draws one held-out sentence
(default tests/data/voice_heldout.wav, its timed phonemes in the .json beside it) with the runtime's TalkingHead
twice:

* top row, "voice model (from audio)": the attached model run by the runtime from the audio (`head.driver.translate`,
  the rows `frames(audio)` draws: overlapping windows, 25 fps rows resampled to the speaker's 30 fps, the silence
  gate);
* bottom row, "phoneme targets": the weights the model was trained to reproduce (exporter/voice/targets.py, 25 fps,
  from the phonemes and the audio's loudness), resampled linearly in time to the same 30 fps frames and played as a
  motion (`head.driver.motion`).

The columns are instants that show distinct visemes, read from the phonemes: a /p b m/ closure, an open vowel, a
rounded vowel, a spread vowel, a pause, then other classes (each at the frame of its segment where the target shape
is strongest, at least 0.1 s apart). Both rows hold the head still at rest, so each cell is the same zoomed view
of the mouth (or, with --crop face, of the face): the speaker's camera narrowed onto the region that jawOpen moves.
Only the chosen frames are drawn; the rows are computed for the whole clip.

Writes the PNG (labelled with Pillow when it is installed, else bare and the labels only in the markdown) and a
markdown file beside it (`--markdown`, default strip.md): the columns with jawOpen and mouthClose of both drives,
where they differ, and the command that wrote them.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shlex
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.runtime import Camera, GaussianTalkerError, HeadPose, TalkingHead
from gaussiantalker.sdk.audio import load_audio
from gaussiantalker.sdk.image import write_png as sdk_write_png
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

ROOT = Path(__file__).resolve().parent.parent
CLIP = ROOT / "tests" / "data" / "voice_heldout.wav"
OUTPUT = ROOT / "docs" / "bench" / "voice" / "strip.png"
ROW_LABELS = ("voice model\n(from audio)", "phoneme\ntargets")
JAW, CLOSE = ARKIT_BLENDSHAPES.index("jawOpen"), ARKIT_BLENDSHAPES.index("mouthClose")
CLOSED_APERTURE = 0.05  # jawOpen - mouthClose at or below this: the lips meet (docs/voice.md, "Measurements")
DIFFERENT_APERTURE = 0.08  # a column whose two apertures differ by more is named in the markdown
DIFFERENT_CHANNEL = 0.15  # ... and one whose any mouth channel differs by more
PROBE_SIZE = 512  # side of the full view in which the mouth is found
CHANGED = 0.1  # a pixel of the probe that the lip shapes change by more (0..1, any channel) belongs to the mouth
# Shapes that move the lips alone (the mouth's box); jawOpen, which also moves the chin, when they move nothing.
LIP_SHAPES = ({"mouthFunnel": 1.0, "mouthSmileLeft": 1.0, "mouthSmileRight": 1.0}, {"jawOpen": 1.0})
CROPS = {"mouth": (2.6, 0.0), "face": (4.0, -0.22)}  # crop side / mouth box side, centre shift / crop side (down)

# What each column may show, in the order columns are given out: (label, visemes of exporter/voice/visemes.py, the
# target channels whose weighted sum says how clearly a frame shows it).
_SPREAD = {"mouthSmileLeft": 0.5, "mouthSmileRight": 0.5, "mouthStretchLeft": 0.5, "mouthStretchRight": 0.5}
CATEGORIES: tuple[tuple[str, tuple[str, ...], dict[str, float]], ...] = (
    # closed lips (aperture jawOpen - mouthClose near 0), the more telling the more jaw they hold shut
    ("closure /p b m/", ("PP",), {"mouthClose": 2.0, "jawOpen": -1.5}),
    ("open /a/", ("aa",), {"jawOpen": 1.0}),
    ("rounded /o/", ("O",), {"mouthFunnel": 1.0, "mouthPucker": 1.0}),
    ("rounded /u w/", ("U", "W"), {"mouthPucker": 1.0, "mouthFunnel": 0.5}),
    ("spread /i/", ("I",), _SPREAD),
    ("silence", ("sil",), {"jawOpen": -1.0, "eyeBlinkLeft": 0.05, "eyeBlinkRight": 0.05}),  # a pause's blink
    ("lip to teeth /f v/", ("FF",), {"mouthRollLower": 1.0}),
    ("mid /e/", ("E",), {"jawOpen": 1.0}),
    ("front rounded /y ø/", ("Y",), {"mouthPucker": 1.0}),
    ("sibilant /s z/", ("SS",), {"mouthStretchLeft": 0.5, "mouthStretchRight": 0.5}),
    ("post-alveolar /ʃ ʒ/", ("CH",), {"mouthFunnel": 1.0}),
    ("rhotic /ɹ/", ("RR",), {"mouthPucker": 1.0}),
    ("schwa /ə/", ("@",), {"jawOpen": 1.0}),
    ("dental /θ ð/", ("TH",), {"tongueOut": 1.0}),
    ("alveolar /t d n l/", ("DD",), {"jawOpen": 1.0}),
    ("velar /k g/", ("kk",), {"jawOpen": 1.0}),
)

app = typer.Typer(add_completion=False)


@dataclass(frozen=True)
class Column:
    """One instant of the strip: the speaker frame, its centre in seconds, the phoneme spoken there ("" in a pause)
    with its word, and what the column is chosen to show."""

    frame: int
    time: float
    phoneme: str
    word: str
    shows: str

    @property
    def heading(self) -> tuple[str, str]:
        """The two lines above the column: time and phoneme, then what it shows."""
        sound = f"/{self.phoneme}/ {self.word}".strip() if self.phoneme else "pause"
        return f"{self.time:.2f} s  {sound}", self.shows


@dataclass
class Strip:
    """What `make_strip` drew: the columns, both rows' weights for the whole clip [T, 52], the cells
    [2, C, size, size, 3] (top row first), the composed image and where each cell sits in it, and the crop."""

    columns: list[Column]
    model: np.ndarray
    targets: np.ndarray
    cells: np.ndarray
    image: np.ndarray
    origins: list[list[tuple[int, int]]]
    crop: tuple[float, float, float]
    labelled: bool
    fps: float
    renderer: str
    text: str
    phonemes: list
    stored: str = "RGB"  # how the PNG holds its pixels (write_png)


# -------------------------------------------------------------------------------------------------- the drives


def load_phonemes(path: Path) -> tuple[list, str]:
    """The timed phonemes and the text of a phoneme json (exporter/voice/data.py `save_utterance`)."""
    from gaussiantalker.exporter.voice.espeak import phonemes_from_json

    meta = json.loads(path.read_text(encoding="utf-8"))
    return phonemes_from_json(meta), str(meta.get("text", ""))


def target_rows(phonemes: Sequence, text: str, audio: np.ndarray, fps: float, frames: int) -> np.ndarray:
    """The phoneme-derived targets (exporter/voice/targets.py, 25 fps; `audio` mono at its 16 kHz) resampled
    linearly in time to `frames` frames at `fps`, frame centres on frame centres, [frames, 52] float32."""
    from gaussiantalker.exporter.voice import targets

    base = targets.arkit_targets(phonemes, text, audio)
    source = (np.arange(base.shape[0]) + 0.5) / targets.FPS
    wanted = (np.arange(frames) + 0.5) / fps
    return np.stack([np.interp(wanted, source, base[:, k]) for k in range(base.shape[1])], 1).astype(np.float32)


def _score_vector(channels: dict[str, float]) -> np.ndarray:
    vector = np.zeros(len(ARKIT_BLENDSHAPES), np.float32)
    for name, weight in channels.items():
        vector[ARKIT_BLENDSHAPES.index(name)] = weight
    return vector


def _word(text: str, position: int) -> str:
    """The word of `text` that starts at (or runs through) character `position`."""
    if not 0 <= position < len(text):
        return ""
    start = position
    while start > 0 and (text[start - 1].isalnum() or text[start - 1] == "'"):
        start -= 1
    match = re.match(r"[\w']+", text[start:])
    return match.group(0) if match else ""


def _spoken_at(phonemes: Sequence, text: str, seconds: float) -> tuple[str, str]:
    """(IPA, word) of the phoneme spoken at `seconds`; ("", "") in a pause or outside the speech."""
    from gaussiantalker.exporter.voice.visemes import PAUSE

    for phoneme in phonemes:
        if phoneme.start <= seconds < phoneme.end:
            if phoneme.ipa == PAUSE:
                return "", ""
            return phoneme.ipa, _word(text, phoneme.text_position)
    return "", ""


def choose_columns(phonemes: Sequence, text: str, targets: np.ndarray, fps: float, seconds: float,
                   count: int = 8, min_gap_s: float = 0.1) -> list[Column]:
    """Up to `count` instants showing distinct visemes, in time order. Every viseme segment of the phonemes
    (exporter/voice/targets.py `segments`: pauses are silence) offers its frames; a frame's score is how clearly the
    target row shows its category (CATEGORIES), with a small preference for the segment's middle. Categories take
    turns in CATEGORIES order, each its best frame at least `min_gap_s` from every chosen one; when every category
    present has a column, the turns go round again."""
    from gaussiantalker.exporter.voice.targets import segments

    frames = targets.shape[0]
    centres = (np.arange(frames) + 0.5) / fps
    offers: list[list[tuple[float, int]]] = [[] for _ in CATEGORIES]
    category_of = {viseme: k for k, (_, visemes, _) in enumerate(CATEGORIES) for viseme in visemes}
    vectors = [_score_vector(channels) for _, _, channels in CATEGORIES]
    for segment in segments(list(phonemes), seconds):
        lo, hi = max(segment.start, 0.0), min(segment.end, seconds)
        kind = category_of.get(segment.viseme)
        if kind is None or hi <= lo:
            continue
        inside = np.nonzero((centres >= lo) & (centres < hi))[0]
        if inside.size == 0:  # a segment shorter than a frame: the frame it falls in
            inside = np.array([min(frames - 1, int((lo + hi) / 2 * fps))])
        middle = (lo + hi) / 2
        for frame in inside:
            nearness = 1.0 - min(1.0, abs(centres[frame] - middle) / max(hi - lo, 1e-6))
            offers[kind].append((float(targets[frame] @ vectors[kind]) + 1e-3 * nearness, int(frame)))
    for offer in offers:
        offer.sort(key=lambda item: -item[0])
    gap = max(1, int(np.ceil(min_gap_s * fps - 1e-9)))
    chosen: list[tuple[int, int]] = []  # (frame, category)
    while len(chosen) < count:
        before = len(chosen)
        for kind, offer in enumerate(offers):
            if len(chosen) >= count:
                break
            taken = next((frame for _, frame in offer if all(abs(frame - f) >= gap for f, _ in chosen)), None)
            if taken is not None:
                chosen.append((taken, kind))
        if len(chosen) == before:
            break
    columns = []
    for frame, kind in sorted(chosen):
        phoneme, word = _spoken_at(phonemes, text, float(centres[frame]))
        columns.append(Column(frame, round(float(centres[frame]), 3), phoneme, word, CATEGORIES[kind][0]))
    return columns


# -------------------------------------------------------------------------------------------------- the view


def changed_box(neutral: np.ndarray, shaped: np.ndarray, threshold: float = CHANGED
                ) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) around the pixels that differ by more than `threshold` between two float frames [H, W, 3]
    of the same view; None if none do."""
    changed = np.abs(shaped.astype(np.float32) - neutral.astype(np.float32)).max(axis=-1) > threshold
    ys, xs = np.nonzero(changed)
    if xs.size == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def mouth_box(head: TalkingHead) -> tuple[int, int, int, int]:
    """The mouth in `head`'s view with the head at rest: the box of what the first of LIP_SHAPES that moves
    anything changes."""
    rest = HeadPose.make()
    neutral = head.render(head.driver.drive(None, rest), "float")
    for shape in LIP_SHAPES:
        box = changed_box(neutral, head.render(head.driver.drive(shape, rest), "float"))
        if box is not None:
            return box
    raise GaussianTalkerError("no lip shape moves anything in view: cannot find the mouth to crop to")


def crop_square(box: tuple[int, int, int, int], crop: str) -> tuple[float, float, float]:
    """(x0, y0, side): the square of `crop` ("mouth" or "face", CROPS) around a mouth box."""
    scale, shift = CROPS[crop]
    side = max(box[2] - box[0], box[3] - box[1]) * scale
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2 + shift * side
    return cx - side / 2, cy - side / 2, side


def crop_camera(camera: Camera, square: tuple[float, float, float], size: int) -> Camera:
    """`camera` narrowed onto a square (x0, y0, side) of its image, drawn at `size` x `size` pixels: the same view
    magnified, not a resampled crop."""
    x0, y0, side = square
    s = size / side
    return Camera(size, size, camera.fx * s, camera.fy * s, (camera.cx - x0) * s, (camera.cy - y0) * s,
                  camera.R, camera.t, camera.near)


def render_cells(head: TalkingHead, rows: Sequence[np.ndarray], frames: Sequence[int]) -> np.ndarray:
    """Each row's weights at each frame, drawn with the head at rest: uint8 [rows, frames, H, W, 3]."""
    rest = HeadPose.make()
    return np.stack([np.stack([head.render(head.driver.drive(weights[frame], rest)) for frame in frames])
                     for weights in rows])


# -------------------------------------------------------------------------------------------------- the picture


def _font(size: int):
    """(font, whether it draws IPA): DejaVu Sans when found, else Pillow's own font (no IPA glyphs)."""
    from PIL import ImageFont

    try:
        return ImageFont.truetype("DejaVuSans.ttf", size), True
    except OSError:
        return ImageFont.load_default(size=size), False


def _ascii_heading(column: Column) -> tuple[str, str]:
    """A heading for a font without IPA: what the column shows stands for the phoneme."""
    sound = column.word or ("pause" if not column.phoneme else "")
    shows = column.shows.split(" /")[0]
    return f"{column.time:.2f} s  {sound}".strip(), shows


def compose(cells: np.ndarray, columns: Sequence[Column], notes: Sequence[Sequence[str]] | None = None,
            row_labels: Sequence[str] = ROW_LABELS, labels: bool = True
            ) -> tuple[np.ndarray, list[list[tuple[int, int]]], bool]:
    """The strip: cells [R, C, h, w, 3] in a grid with a 1/96-cell gap, and with Pillow (when `labels` and it is
    installed) the row labels on the left, each column's heading above it and its note (`notes[r][c]`) under each
    cell. Returns (uint8 image [H, W, 3], the (x, y) of each cell's top-left corner, whether it is labelled)."""
    rows, count, height, width = cells.shape[:4]
    gap = max(1, width // 96)
    try:
        from PIL import Image, ImageDraw
    except ImportError:
        labels = False
    if not labels:
        image = np.full((rows * height + (rows - 1) * gap, count * width + (count - 1) * gap, 3), 255, np.uint8)
        origins = [[(c * (width + gap), r * (height + gap)) for c in range(count)] for r in range(rows)]
        for r in range(rows):
            for c in range(count):
                x, y = origins[r][c]
                image[y:y + height, x:x + width] = cells[r, c]
        return image, origins, False
    font, ipa = _font(max(9, width // 13))
    small, _ = _font(max(8, width // 16))
    line = font.getbbox("Ag/ɑ")[3] + max(2, width // 64)
    note_height = small.getbbox("Ag0")[3] + max(2, width // 64) if notes is not None else 0
    pad = max(3, width // 24)
    scratch = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    margin = max(scratch.multiline_textbbox((0, 0), label, font=font)[2] for label in row_labels) + 2 * pad
    top = 2 * line + pad
    origins = [[(margin + c * (width + gap), top + r * (height + note_height + gap)) for c in range(count)]
               for r in range(rows)]
    canvas = Image.new("RGB", (margin + count * width + (count - 1) * gap,
                               top + rows * (height + note_height) + (rows - 1) * gap), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for r in range(rows):
        for c in range(count):
            x, y = origins[r][c]
            canvas.paste(Image.fromarray(np.ascontiguousarray(cells[r, c])), (x, y))
            if notes is not None:
                draw.text((x + width / 2, y + height + 1), notes[r][c], fill=(60, 60, 60), font=small, anchor="ma")
        x, y = pad, origins[r][0][1] + height / 2
        draw.multiline_text((x, y), row_labels[r], fill=(0, 0, 0), font=font, anchor="lm")
    for c, column in enumerate(columns):
        first, second = column.heading if ipa else _ascii_heading(column)
        x = origins[0][c][0] + width / 2
        draw.text((x, pad // 2), first, fill=(0, 0, 0), font=font, anchor="ma")
        draw.text((x, pad // 2 + line), second, fill=(90, 90, 90), font=font, anchor="ma")
    return np.asarray(canvas), origins, True


def write_png(path: Path, image: np.ndarray, max_bytes: int | None = None) -> str:
    """Write an RGB image; one over `max_bytes` is written again as 256 adaptive colours (Pillow). Returns how it
    was stored ("RGB", "256 colours", or "RGB, over the limit")."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        from PIL import Image
    except ImportError:
        sdk_write_png(path, image)
        return "RGB" if max_bytes is None or path.stat().st_size <= max_bytes else "RGB, over the limit"
    picture = Image.fromarray(np.ascontiguousarray(image))
    picture.save(path, optimize=True)
    if max_bytes is None or path.stat().st_size <= max_bytes:
        return "RGB"
    picture.quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)
    return "256 colours"


# -------------------------------------------------------------------------------------------------- the avatar


def import_with_voice(avatar: Path, folder: Path, progress: bool = False) -> Path:
    """Import a LAM avatar zip, attach the built-in voice, save its checkpoint and export its bundle into `folder`
    (as `gt-import lam` and `gt-export` do); returns the bundle's path."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint
    from gaussiantalker.exporter.imports.sources.lam import LamOptions, import_lam
    from gaussiantalker.exporter.voice.attach import builtin_audio_model

    speaker = import_lam(avatar, LamOptions(), progress=progress)
    speaker.audio_model = builtin_audio_model(speaker)
    checkpoint = save_checkpoint(speaker, folder / "avatar.ckpt")
    bundle = folder / "avatar.gtb"
    export_bundle(load_checkpoint(checkpoint), bundle, progress=progress)
    return bundle


def _notes(columns: Sequence[Column], rows: Sequence[np.ndarray]) -> list[list[str]]:
    return [[f"jaw {w[c.frame, JAW]:.2f}  close {w[c.frame, CLOSE]:.2f}" for c in columns] for w in rows]


def make_strip(bundle: Path, audio_path: Path, phonemes_path: Path, output: Path, *, count: int = 8,
               cell: int = 192, crop: str = "mouth", renderer: str | None = None, max_bytes: int | None = 300_000,
               labels: bool = True, log: Callable[[str], None] = lambda _: None) -> Strip:
    """Draw the strip of `bundle` (an ARKit speaker with an audio model) saying `audio_path` and write it to
    `output` (PNG); returns what was drawn."""
    from gaussiantalker.exporter.voice.targets import SAMPLE_RATE

    if crop not in CROPS:
        raise GaussianTalkerError(f"crop must be one of {', '.join(CROPS)}, got {crop!r}")
    phonemes, text = load_phonemes(phonemes_path)
    with TalkingHead(bundle, resolution=(PROBE_SIZE, PROBE_SIZE), renderer=renderer, composite=False) as probe:
        samples = probe.driver.load_audio(audio_path)
        model = probe.driver.translate(samples)  # the rows frames(audio) draws
        fps, seconds, camera = probe.fps, samples.shape[0] / probe.sample_rate, probe.camera
        targets = np.asarray(probe.driver.motion(target_rows(phonemes, text, load_audio(audio_path, SAMPLE_RATE), fps,
                                                      model.shape[0])).weights, np.float32)
        square = crop_square(mouth_box(probe), crop)
    columns = choose_columns(phonemes, text, targets, fps, seconds, count)
    log(f"{len(columns)} columns at frames {[c.frame for c in columns]}, crop {crop} "
        f"({square[2]:.0f} px of the {PROBE_SIZE} px view)")
    with TalkingHead(bundle, camera=crop_camera(camera, square, cell), renderer=renderer, composite=False) as head:
        cells = render_cells(head, (model, targets), [c.frame for c in columns])
        used = head.renderer
    image, origins, labelled = compose(cells, columns, _notes(columns, (model, targets)), labels=labels)
    stored = write_png(output, image, max_bytes)
    log(f"wrote {output} ({image.shape[1]}x{image.shape[0]}, {output.stat().st_size / 1e3:.0f} kB, {stored})")
    return Strip(columns, model, targets, cells, image, origins, square, labelled, fps, used, text, phonemes, stored)


# -------------------------------------------------------------------------------------------------- the table


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    scale = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / scale) if scale > 0 else float("nan")


def closures(weights: np.ndarray, phonemes: Sequence, fps: float) -> list[tuple[float, float]]:
    """(start in seconds, smallest aperture) of each /p b m/ run, the aperture taken from a frame before the run to a
    frame after it: docs/voice.md's closure measure at the speaker's frame rate (closed: at most CLOSED_APERTURE)."""
    from gaussiantalker.exporter.voice.evaluate import bilabial_onsets

    aperture = weights[:, JAW] - weights[:, CLOSE]
    out = []
    for start, end in bilabial_onsets(list(phonemes)):
        first = int(np.floor(start * fps))
        last = max(first, int(np.ceil(end * fps)) - 1)
        window = aperture[max(0, first - 1): min(len(aperture), last + 2)]
        if window.size:
            out.append((start, float(window.min())))
    return out


def differences(strip: Strip) -> list[str]:
    """One sentence per column where the two drives differ visibly: apertures more than DIFFERENT_APERTURE apart,
    or a mouth channel more than DIFFERENT_CHANNEL apart."""
    mouth = [k for k, name in enumerate(ARKIT_BLENDSHAPES) if name.startswith(("jaw", "mouth", "tongue"))]
    out = []
    for index, column in enumerate(strip.columns, 1):
        m, t = strip.model[column.frame], strip.targets[column.frame]
        said = []
        am, at = m[JAW] - m[CLOSE], t[JAW] - t[CLOSE]
        if abs(am - at) > DIFFERENT_APERTURE:
            how = "closed" if am <= CLOSED_APERTURE else ("wider open" if am > at else "less open")
            said.append(f"the model's lips are {how} (aperture {am:.2f} against {at:.2f})")
        gaps = np.abs(m[mouth] - t[mouth])
        worst = int(np.argmax(gaps))
        if gaps[worst] > DIFFERENT_CHANNEL:
            name = ARKIT_BLENDSHAPES[mouth[worst]]
            said.append(f"{name} {m[mouth[worst]]:.2f} against {t[mouth[worst]]:.2f}")
        if said:
            first, _ = column.heading
            out.append(f"* column {index} ({first}, {column.shows}): " + "; ".join(said) + ".")
    return out


def markdown(strip: Strip, png: Path, audio: Path, avatar: str, command: str, seconds: float,
             source: str | None = None, recording: str | None = None) -> str:
    """strip.md: what the strip shows, its columns with jawOpen / mouthClose of both drives, where they differ."""
    fps, text = strip.fps, strip.text
    rows = ["| # | time | phoneme | word | shows | jawOpen model / target | mouthClose model / target | "
            "aperture model / target |", "|---:|---:|---|---|---|---:|---:|---:|"]
    for index, column in enumerate(strip.columns, 1):
        m, t = strip.model[column.frame], strip.targets[column.frame]
        sound = f"/{column.phoneme}/" if column.phoneme else "(pause)"
        rows.append(f"| {index} | {column.time:.2f} s | {sound} | {column.word} | {column.shows} | "
                    f"{m[JAW]:.2f} / {t[JAW]:.2f} | {m[CLOSE]:.2f} / {t[CLOSE]:.2f} | "
                    f"{m[JAW] - m[CLOSE]:.2f} / {t[JAW] - t[CLOSE]:.2f} |")
    differ = differences(strip)
    model_runs, target_runs = closures(strip.model, strip.phonemes, fps), closures(strip.targets, strip.phonemes, fps)
    model_closed = sum(smallest <= CLOSED_APERTURE for _, smallest in model_runs)
    target_closed, runs = sum(smallest <= CLOSED_APERTURE for _, smallest in target_runs), len(model_runs)
    for (start, smallest), (_, target) in zip(model_runs, target_runs, strict=True):
        if smallest > CLOSED_APERTURE >= target:
            ipa, word = _spoken_at(strip.phonemes, text, start + 1e-6)
            differ.append(f"* /{ipa}/ at {start:.2f} s ({word}): the model's lips come no closer than "
                          f"aperture {smallest:.3f} where the targets close them ({target:.3f}).")
    first = strip.phonemes[0] if strip.phonemes else None
    if first is not None and first.start < 0.05 and first.ipa != "_":
        lead = (" Speech starts at the clip's first sample, with no silence before it (docs/voice.md measures its "
                "clips with 0.3 s of silence put before them).")
    else:
        lead = ""
    blink = ARKIT_BLENDSHAPES.index("eyeBlinkLeft")
    blinks = [f"column {k} ({c.time:.2f} s: eyeBlink model {strip.model[c.frame, blink]:.2f} / target "
              f"{strip.targets[c.frame, blink]:.2f})" for k, c in enumerate(strip.columns, 1)
              if max(strip.model[c.frame, blink], strip.targets[c.frame, blink]) > 0.3]
    blinks_said = (" In a blink: " + ", ".join(blinks) + "; the targets blink at the start of each pause after "
                   "speech (docs/voice.md, \"Targets\").") if blinks else ""
    aperture_m = strip.model[:, JAW] - strip.model[:, CLOSE]
    aperture_t = strip.targets[:, JAW] - strip.targets[:, CLOSE]
    jaw_r = _pearson(strip.model[:, JAW], strip.targets[:, JAW])
    try:
        shown = audio.resolve().relative_to(ROOT)
    except ValueError:
        shown = audio
    said = f"`{shown}`" if recording is None else recording
    lines = [
        "# The built-in voice, frame by frame",
        "",
        f"![{len(strip.columns)} instants of one sentence, the voice model above the phoneme targets]({png.name})",
        "",
        f"One sentence ({said}, {strip.model.shape[0] / fps:.2f} s: \"{text}\") said by an imported LAM "
        f"avatar ({avatar}) with the built-in voice attached (docs/voice.md), drawn twice at the same "
        f"{fps:g} fps frames, the head held at rest:",
        "",
        "* **top, voice model (from audio)**: `exporter/voice/models/arkit_voice.onnx` run by the runtime from "
        "the audio (`head.driver.translate`, the rows `frames(audio)` draws: overlapping windows, its 25 fps rows "
        f"resampled to {fps:g} fps, the silence gate);",
        "* **bottom, phoneme targets**: the weights it was trained to reproduce (`exporter/voice/targets.py`, from "
        "the timed phonemes and the audio's loudness, 25 fps), resampled linearly in time to the same frames.",
        "",
        "Each column is an instant chosen from the phonemes to show one viseme class (the frame of the segment where "
        "the target shape is strongest); under each cell its drive's jawOpen and mouthClose. ARKit's mouthClose "
        "shuts the lips on an open jaw, so the lips' opening is the aperture jawOpen - mouthClose (at most "
        f"{CLOSED_APERTURE} counts as closed).",
        "",
        *rows,
        "",
        f"Over the whole clip ({strip.model.shape[0]} frames): jawOpen r {jaw_r:.3f}, "
        f"aperture r {_pearson(aperture_m, aperture_t):.3f}, mean |difference| of the aperture "
        f"{np.abs(aperture_m - aperture_t).mean():.3f}; /p b m/ runs closed within a frame: model {model_closed} of "
        f"{runs}, targets {target_closed} of {runs}.{lead}{blinks_said}",
        "",
        "## Where the rows differ",
        "",
        *(differ or [f"No column's aperture differs by more than {DIFFERENT_APERTURE} or mouth channel by more "
                     f"than {DIFFERENT_CHANNEL}."]),
        "",
        "## Reproduce",
        "",
        "```bash",
        command,
        "```",
        "",
        *([f"The avatar: {source}.", ""] if source else []),
        f"{seconds:.0f} s on {os.cpu_count()} {platform.machine()} cores (import, attach, export, "
        f"{2 * len(strip.columns)} frames with the {strip.renderer} renderer; the PNG in {strip.stored}). The avatar, "
        "its checkpoint and its bundle live in a temporary folder only; the strip and this file are what the command "
        "keeps.",
        "",
    ]
    return "\n".join(lines)


def real_recording(clip_id: str, folder: Path) -> tuple[Path, Path, str]:
    """A fetched real recording (exporter/voice/real_speech.py) aligned by pocketsphinx, written into `folder` as
    the wav and phoneme json `make_strip` reads; and how the markdown names it."""
    from gaussiantalker.exporter.voice import real_speech
    from gaussiantalker.exporter.voice.align import align
    from gaussiantalker.exporter.voice.data import save_utterance
    from gaussiantalker.exporter.voice.espeak import Utterance

    sources = {source.id: source for source in real_speech.CLIPS}
    if clip_id not in sources:
        raise GaussianTalkerError(f"--real {clip_id!r}: no such recording (one of {', '.join(sources)})")
    try:
        clip = real_speech.load(clips=[sources[clip_id]])[0]
    except real_speech.RealSpeechMissing as exc:
        raise GaussianTalkerError(str(exc)) from None
    alignment = align(clip.audio, clip.transcript)
    save_utterance(Utterance(clip.transcript, f"real:{clip_id}", clip.audio, alignment.phonemes), folder / clip_id)
    source = sources[clip_id]
    quality = "a poor alignment" if alignment.poor else "a good alignment"
    said = (f"the real recording `{clip_id}` ({source.speaker}; {source.source}), its phonemes aligned to the "
            f"transcript by pocketsphinx ({quality}: mean score {alignment.mean_score:.2f} nats per frame)")
    return folder / f"{clip_id}.wav", folder / f"{clip_id}.json", said


@app.command()
def main(
    avatar: Path = typer.Argument(..., help="LAM avatar zip (as LAM_WebRender and OpenAvatarChat ship them)"),
    audio: Path = typer.Option(CLIP, "--audio", "-a", help="the sentence (a wav or anything ffmpeg "
                               "reads)"),
    phonemes: Path = typer.Option(None, "--phonemes", help="its timed phonemes (exporter/voice/data.py "
                                  "save_utterance's json) [default: AUDIO with .json]"),
    output: Path = typer.Option(OUTPUT, "-o", "--output", help="the PNG to write"),
    markdown_path: Path = typer.Option(None, "--markdown", help="the markdown to write [default: strip.md beside "
                                       "the PNG]"),
    columns: int = typer.Option(8, "--columns", "-n", min=1, max=32, help="instants to show"),
    cell: int = typer.Option(192, "--cell", min=16, max=1024, help="side of each cell, pixels"),
    crop: str = typer.Option("mouth", "--crop", help="what a cell shows: face or mouth"),
    renderer: str = typer.Option(None, "--renderer", help="gl, cpu or auto [default: the bundle's]"),
    max_kb: int = typer.Option(300, "--max-kb", min=1, help="a PNG larger than this is stored in 256 colours"),
    source: str = typer.Option(None, "--source", help="where the avatar comes from, said in the markdown"),
    real: str = typer.Option(None, "--real", help="say this real recording instead (an id of exporter/voice/"
                             "real_speech.py, fetched at install), its phonemes aligned by pocketsphinx"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress"),
) -> None:
    """Import AVATAR, attach the built-in voice and draw a sentence as the model says it and as its targets do."""
    start = time.perf_counter()
    phonemes = phonemes or audio.with_suffix(".json")
    markdown_path = markdown_path or output.with_name("strip.md")
    log = (lambda _: None) if quiet else typer.echo
    try:
        if not avatar.is_file():
            raise GaussianTalkerError(f"avatar zip {avatar} does not exist")
        with tempfile.TemporaryDirectory(prefix="gt-voice-strip-") as folder:
            recording = None
            if real is not None:
                audio, phonemes, recording = real_recording(real, Path(folder))
            bundle = import_with_voice(avatar, Path(folder), progress=not quiet)
            strip = make_strip(bundle, audio, phonemes, output, count=columns, cell=cell, crop=crop,
                               renderer=renderer, max_bytes=max_kb * 1000, log=log)
        command = shlex.join(["python", "samples/voice_strip.py", *sys.argv[1:]]) if sys.argv[1:] else \
            f"python samples/voice_strip.py {shlex.quote(str(avatar))}"
        seconds = time.perf_counter() - start
        markdown_path.parent.mkdir(parents=True, exist_ok=True)
        markdown_path.write_text(markdown(strip, output, audio, f"`{avatar.name}`", command, seconds,
                                          source, recording),
                                 encoding="utf-8")
    except GaussianTalkerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"wrote {output} and {markdown_path} in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    app()
