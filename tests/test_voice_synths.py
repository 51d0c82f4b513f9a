"""festival and flite as training-speech sources (exporter/voice/festival.py, flite.py, segments.py; docs/voice.md,
"Voices"): two voices of each speak a few sentences, and their audio and timed phonemes are checked the way the
targets use them: 16 kHz finite audio, contiguous phonemes covering it, ARPAbet mapped to known IPA, stressed
vowels, each phoneme's word in the text (a question's words before its '?'), tempo, determinism (within a batch,
after other settings, across processes), awkward text, and errors that name the problem.

The engines are Debian packages that .ci/install installs; these tests skip where one is missing, and fail instead
where CI is set. A festival batch is one process (~0.2-0.5 s), so each voice speaks all its sentences at once.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
from functools import cache

import numpy as np
import pytest
from ci_tools import need

from gaussiantalker.exporter.voice import festival, flite, targets, visemes
from gaussiantalker.exporter.voice.espeak import PAUSE, SAMPLE_RATE, Utterance
from gaussiantalker.exporter.voice.segments import Request, token_offsets

ENGINES = {"festival": festival, "flite": flite}
INSTALLS = {"festival": ".ci/install (Debian packages festival festvox-us-slt-hts festvox-kallpc16k festvox-kdlpc16k)",
            "flite": ".ci/install (Debian package flite, which brings libflite1)"}
CASES = [("festival", "slt_hts"), ("festival", "kal"), ("flite", "slt"), ("flite", "kal16")]
BILABIAL = "Maybe Bob bought the map."
QUESTION = "Did Bob see the map? He did."
AWKWARD = 'She said "stop" (twice) \\ then\nleft; it\'s at C:\\temp\\\\x.'
OTHER = Request("Peter picked a peck of pickled peppers!", "", 0.8, 150.0)  # voice filled in per case


def _need(engine: str, voice: str) -> None:
    module = ENGINES[engine]
    if not module.available():
        need(f"{engine} is not installed (Debian: apt-get install {engine})", INSTALLS[engine])
    elif not module.available(voice):
        need(f"{engine}'s voice {voice!r} is not installed", INSTALLS[engine])


@cache
def _spoken(engine: str, voice: str) -> tuple[Utterance, ...]:
    """[BILABIAL, QUESTION, AWKWARD, BILABIAL at tempo 1.3, OTHER, BILABIAL]: one batch (one festival process)."""
    requests = [Request(BILABIAL, voice), Request(QUESTION, voice), Request(AWKWARD, voice),
                Request(BILABIAL, voice, 1.3), Request(OTHER.text, voice, OTHER.tempo, OTHER.pitch),
                Request(BILABIAL, voice)]
    return tuple(ENGINES[engine].synthesize_many(requests))


@pytest.fixture(params=CASES, ids=[f"{e}-{v}" for e, v in CASES])
def case(request) -> tuple[str, str, tuple[Utterance, ...]]:
    engine, voice = request.param
    _need(engine, voice)
    return engine, voice, _spoken(engine, voice)


def _spoken_names(utterance: Utterance) -> list[str]:
    return [p.ipa for p in utterance.phonemes if p.ipa != PAUSE]


def test_audio_and_phonemes_cover_each_other(case):
    engine, voice, spoken = case
    for u in spoken:
        assert u.voice == f"{engine}:{voice}"
        assert u.audio.dtype == np.float32 and u.audio.ndim == 1 and np.isfinite(u.audio).all()
        assert 0.5 < u.seconds < 10.0 and np.sqrt(np.mean(u.audio ** 2)) > 0.01  # 16 kHz speech, not silence
        assert u.phonemes[0].start == 0.0 and u.phonemes[-1].end == pytest.approx(u.seconds, abs=1e-6)
        assert all(p.end > p.start for p in u.phonemes)
        assert all(a.end == b.start for a, b in zip(u.phonemes, u.phonemes[1:], strict=False))
        assert len(_spoken_names(u)) >= 8
    assert SAMPLE_RATE == 16000


def test_names_stress_and_words(case):
    _, _, spoken = case
    bilabial, question = spoken[0], spoken[1]
    names = _spoken_names(bilabial)
    assert names.count("b") == 4 and names.count("m") == 2 and names.count("p") == 1
    for u in spoken:  # every IPA symbol is in the viseme table: nothing falls back to the neutral viseme
        unknown = {s for p in u.phonemes if p.ipa != PAUSE for s in visemes.symbols_of(p.ipa)} - set(visemes.SYMBOLS)
        assert not unknown
        stressed = [p for p in u.phonemes if p.stress == 1]
        assert stressed and all(visemes.visemes_of(p.ipa)[0][0] in visemes.VOWEL_VISEMES for p in stressed)
    # each phoneme's text_position is its word's; a pause's is the next word's (the end of the text at the end)
    assert sorted({p.text_position for p in bilabial.phonemes if p.ipa != PAUSE}) == token_offsets(
        BILABIAL, BILABIAL.rstrip(".").split())
    spoken_q = [p for p in question.phonemes if p.ipa != PAUSE]
    positions = [p.text_position for p in spoken_q]
    assert positions == sorted(positions)
    assert set(positions) == set(token_offsets(QUESTION, ["Did", "Bob", "see", "the", "map", "He", "did"]))
    map_phonemes = [p for p in spoken_q if p.text_position == QUESTION.index("map")]
    assert [p.ipa for p in map_phonemes] == ["m", "æ", "p"] and QUESTION.index("map") < QUESTION.index("?")
    after_map = question.phonemes[question.phonemes.index(map_phonemes[-1]) + 1]
    assert after_map.ipa == PAUSE and after_map.text_position == QUESTION.index("He")  # the pause at '?'
    assert [is_question for _, is_question in targets._clauses(question.phonemes, QUESTION)] == [True, False]
    assert question.phonemes[-1].ipa == PAUSE and question.phonemes[-1].text_position == len(QUESTION)


def test_awkward_text_is_spoken(case):
    _, _, spoken = case
    awkward = spoken[2]
    positions = {p.text_position for p in awkward.phonemes if p.ipa != PAUSE}
    assert {AWKWARD.index("stop"), AWKWARD.index("twice"), AWKWARD.index("left")} <= positions
    assert awkward.seconds > 1.5


def test_tempo_and_settings(case):
    engine, voice, spoken = case
    slow = spoken[3]
    assert slow.seconds / spoken[0].seconds == pytest.approx(1.3, abs=0.06)
    assert slow.settings["tempo"] == 1.3
    pitch = spoken[4].settings["pitch"]
    assert pitch == (None if voice in ENGINES[engine].FIXED_PITCH else OTHER.pitch)


def test_deterministic_after_other_settings_and_across_processes(case):
    engine, voice, spoken = case
    first, again = spoken[0], spoken[5]
    assert np.array_equal(first.audio, again.audio) and first.phonemes == again.phonemes
    digest = hashlib.sha256(first.audio.tobytes()).hexdigest()
    code = (f"import hashlib; from gaussiantalker.exporter.voice import {engine} as m; "
            f"print(hashlib.sha256(m.synthesize({BILABIAL!r}, {voice!r}).audio.tobytes()).hexdigest())")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert done.stdout.strip() == digest


@pytest.mark.parametrize("engine", list(ENGINES))
def test_bad_requests_name_the_problem(engine):
    module = ENGINES[engine]
    if not module.available():
        need(f"{engine} is not installed (Debian: apt-get install {engine})", INSTALLS[engine])
    error = module.FestivalError if engine == "festival" else module.FliteError
    voice = next(iter(module.VOICES))
    with pytest.raises(error, match="no voice 'nobody'"):
        module.synthesize(BILABIAL, "nobody")
    with pytest.raises(error, match="empty text"):
        module.synthesize(" \n\t", voice)
    with pytest.raises(error, match="tempo"):
        module.synthesize(BILABIAL, voice, tempo=0.0)
    assert not module.available("nobody")


def test_scheme_strings_are_escaped():
    assert festival.scheme_string('a"b\\c\nd\x00e') == '"a\\"b\\\\c d e"'
    assert token_offsets("Bob, bob? BOB", ["bob", "Bob", "bob", "nope"]) == [0, 5, 10, 13]
