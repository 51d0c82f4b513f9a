"""The voice strip sample (samples/voice_strip.py) end to end at tiny size, on a synthetic LAM avatar."""

from __future__ import annotations

import importlib.util
import struct
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CLIP = ROOT / "tests" / "data" / "voice_heldout"
CELL = 32


def _sample():
    """samples/voice_strip.py as a module (a script, not a package module)."""
    spec = importlib.util.spec_from_file_location("sample_voice_strip", ROOT / "samples" / "voice_strip.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_voice_strip_on_a_synthetic_avatar(lam_voice_bundle, tmp_path):
    """On the synthetic LAM avatar with the built-in voice (the session's bundle): choose the columns from the
    held-out clip's phonemes, draw both rows and compose the strip. The PNG holds the composed grid, the columns
    show distinct visemes in time order, and the two rows differ exactly where their drives differ."""
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

    strip_module = _sample()
    bundle = lam_voice_bundle
    png = tmp_path / "out" / "strip.png"
    strip = strip_module.make_strip(bundle, CLIP.with_suffix(".wav"), CLIP.with_suffix(".json"), png, count=6,
                                    cell=CELL, max_bytes=None)

    columns = strip.columns
    assert len(columns) == 6 and [c.frame for c in columns] == sorted({c.frame for c in columns})
    assert min(np.diff([c.frame for c in columns])) >= 3  # at least 0.1 s apart at 30 fps
    shows = [c.shows for c in columns]
    assert len(set(shows)) == 6
    assert {"closure /p b m/", "open /a/", "rounded /o/", "spread /i/", "silence"} <= set(shows)
    closure = columns[shows.index("closure /p b m/")]
    assert closure.phoneme in ("p", "b", "m") and strip.targets[closure.frame, strip_module.CLOSE] > 0
    assert columns[shows.index("silence")].phoneme == ""
    assert columns[shows.index("open /a/")].word == "Bob's"
    assert strip.model.shape == strip.targets.shape == (141, 52)  # 4.7 s at 30 fps

    # The PNG is the composed image; every cell sits at its origin.
    width, height = struct.unpack(">II", png.read_bytes()[16:24])
    assert (height, width) == strip.image.shape[:2]
    assert strip.cells.shape == (2, 6, CELL, CELL, 3)
    assert height >= 2 * CELL and width >= 6 * CELL
    for r in range(2):
        for c in range(6):
            x, y = strip.origins[r][c]
            assert np.array_equal(strip.image[y:y + CELL, x:x + CELL], strip.cells[r, c])
    assert (tmp_path / "out" / "strip.png").stat().st_size > 0

    # The rows differ exactly where the drives differ: the model's own rows against a copy with the jaw of
    # every other column moved.
    moved = strip.model.copy()
    frames = [c.frame for c in columns]
    jaw = ARKIT_BLENDSHAPES.index("jawOpen")
    for frame in frames[::2]:
        moved[frame, jaw] = 0.9 if moved[frame, jaw] < 0.45 else 0.0
    with TalkingHead(bundle, resolution=(strip_module.PROBE_SIZE,) * 2, composite=False) as probe:
        camera = strip_module.crop_camera(probe.camera, strip.crop, CELL)
    with TalkingHead(bundle, camera=camera, composite=False) as head:
        cells = strip_module.render_cells(head, (strip.model, moved), frames)
    assert np.array_equal(cells[0], strip.cells[0])  # the same drives draw the same cells
    image, origins, _ = strip_module.compose(cells, columns, labels=False)
    for c in range(6):
        (x0, y0), (x1, y1) = origins[0][c], origins[1][c]
        top, bottom = image[y0:y0 + CELL, x0:x0 + CELL], image[y1:y1 + CELL, x1:x1 + CELL]
        assert np.array_equal(top, bottom) == (c % 2 == 1), c


def test_real_recording_is_aligned_for_the_strip(tmp_path):
    """`--real ID`: a fetched real recording and its pocketsphinx phonemes, written as the wav and json the strip
    reads; an unknown id is refused with the ids there are."""
    import pytest
    from ci_tools import need

    from gaussiantalker.exporter.voice import real_speech
    from gaussiantalker.exporter.voice.data import load_utterance
    from gaussiantalker.runtime import GaussianTalkerError

    strip_module = _sample()
    with pytest.raises(GaussianTalkerError, match="no such recording.*librivox-0920"):
        strip_module.real_recording("nope", tmp_path)
    try:
        audio, phonemes, said = strip_module.real_recording("librivox-0920", tmp_path)
    except GaussianTalkerError as exc:
        need(str(exc), ".ci/install (python -m gaussiantalker.exporter.voice.real_speech fetch)")
        raise
    utterance = load_utterance(audio.with_suffix(""))
    assert phonemes == audio.with_suffix(".json") and "pocketsphinx" in said and "librivox-0920" in said
    assert utterance.text == next(c.transcript for c in real_speech.CLIPS if c.id == "librivox-0920")
    assert sum(p.ipa in ("p", "b", "m") for p in utterance.phonemes) >= 8  # married, more, amiable, woman, might, ...
    assert abs(utterance.phonemes[-1].end - utterance.seconds) < 1e-3
