"""Text a page asks the server to speak, spoken by espeak-ng with no client text on its command line: the text
goes on stdin, the command line is fixed, and the run is bounded in length, time, output and concurrency
(docs/serve.md, "Threat model")."""

from __future__ import annotations

import asyncio
import shutil
import tempfile
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.audio import load_audio
from gaussiantalker.sdk.errors import GaussianTalkerError

RATE = 16000


class SpeechError(ValueError):
    """The text cannot be spoken: no espeak-ng, too long, or the synthesiser failed or ran past its bounds."""


def synthesiser() -> str | None:
    """The espeak-ng (or espeak) executable, or None."""
    return shutil.which("espeak-ng") or shutil.which("espeak")


async def speak(text: str, *, max_chars: int, timeout_s: float, max_bytes: int,
                gate: asyncio.Semaphore) -> tuple[np.ndarray, int]:
    """`text` spoken: mono samples at RATE. The synthesiser reads the text from stdin (its arguments are fixed:
    no text can become an option or a file name), at most `gate`'s count run at once, each killed after
    `timeout_s` or once it has written `max_bytes`."""
    if not isinstance(text, str):
        raise SpeechError("text must be a string")
    if len(text) > max_chars:
        raise SpeechError(f"text is {len(text)} characters: at most {max_chars} are spoken")
    if not text.strip():
        raise SpeechError("text is empty")
    exe = synthesiser()
    if exe is None:
        raise SpeechError("text-to-speech needs espeak-ng on the server")
    async with gate:
        process = await asyncio.create_subprocess_exec(
            exe, "--stdout", stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.DEVNULL)
        try:
            wav = await asyncio.wait_for(_bounded_output(process, text.encode("utf-8"), max_bytes), timeout_s)
        except asyncio.TimeoutError:
            raise SpeechError(f"the synthesiser took longer than {timeout_s:g} s") from None
        finally:
            if process.returncode is None:
                process.kill()
            await process.wait()
    if process.returncode != 0:
        raise SpeechError("the synthesiser failed")
    try:
        samples = await asyncio.get_running_loop().run_in_executor(None, _decoded, wav)
    except (GaussianTalkerError, ValueError, TypeError):
        raise SpeechError("the synthesiser's output could not be read") from None
    return samples, RATE


def _decoded(wav: bytes) -> np.ndarray:
    """espeak-ng's wav decoded at RATE, through a private temporary file (ffmpeg reads files)."""
    with tempfile.TemporaryDirectory(prefix="gt-serve-speech-") as folder:
        path = Path(folder) / "speech.wav"
        path.write_bytes(wav)
        return load_audio(path, RATE)


async def _bounded_output(process: asyncio.subprocess.Process, stdin: bytes, max_bytes: int) -> bytes:
    """Write `stdin`, close it, and read stdout to its end; SpeechError past max_bytes."""
    assert process.stdin is not None and process.stdout is not None
    process.stdin.write(stdin)
    await process.stdin.drain()
    process.stdin.close()
    chunks, size = [], 0
    while chunk := await process.stdout.read(65536):
        size += len(chunk)
        if size > max_bytes:
            raise SpeechError(f"the spoken text is longer than {max_bytes} bytes of audio")
        chunks.append(chunk)
    await process.wait()
    return b"".join(chunks)


__all__ = ["RATE", "SpeechError", "speak", "synthesiser"]
