"""Pushed audio of a live session: chunks of any size, dtype and rate in, two aligned sample queues out.

One queue holds the audio at the speaker's rate (what the translator hears), the other at the session's output
rate (what each LiveFrame carries for the app's transport). Both are cut by the same video-frame clock, so they
stay aligned however the chunks were sized. Resampling streams through libsoxr (python-soxr's ResampleStream):
resampling each chunk on its own would put a filter edge, an audible click, at every chunk border
(docs/live.md, "The timeline and the audio clock").
"""

from __future__ import annotations

import numpy as np
import soxr

from gaussiantalker.sdk.audio import RESAMPLE_QUALITY


class SampleFifo:
    """A first-in first-out queue of float32 samples in one growing buffer (appends amortised, reads are views)."""

    def __init__(self) -> None:
        self._buffer = np.zeros(4096, np.float32)
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, samples: np.ndarray) -> None:
        count = samples.shape[0]
        if self._end + count > self._buffer.shape[0]:
            held = self._buffer[self._start:self._end]
            grown = np.zeros(max(self._buffer.shape[0], 2 * (held.shape[0] + count)), np.float32)
            grown[: held.shape[0]] = held
            self._buffer, self._start, self._end = grown, 0, held.shape[0]
        self._buffer[self._end:self._end + count] = samples
        self._end += count

    def peek(self, count: int) -> np.ndarray:
        """The first `count` samples (a copy), zero-padded when fewer are queued."""
        if count <= len(self):  # the usual case: one copy, no zero fill
            return self._buffer[self._start:self._start + count].copy()
        out = np.zeros(count, np.float32)
        held = min(count, len(self))
        out[:held] = self._buffer[self._start:self._start + held]
        return out

    def take(self, count: int) -> np.ndarray:
        """Remove and return the first `count` samples, zero-padded when fewer are queued."""
        out = self.peek(count)
        self.skip(count)
        return out

    def head(self, count: int) -> np.ndarray:
        """A view of the first `count` samples (at most len(self)), valid until the next append."""
        return self._buffer[self._start:self._start + min(count, len(self))]

    def skip(self, count: int) -> None:
        """Remove the first `count` samples (all of them when fewer are queued) without copying them."""
        self._start += min(count, len(self))
        if self._start == self._end:
            self._start = self._end = 0

    def clear(self) -> None:
        self._start = self._end = 0


class ResampledQueue:
    """Pushed mono audio resampled to one fixed rate, streamed (filter state carried across chunks)."""

    def __init__(self, rate: int) -> None:
        self.rate = rate
        self.samples = SampleFifo()
        self._source_rate: int | None = None
        self._stream: soxr.ResampleStream | None = None

    def push(self, mono: np.ndarray, source_rate: int) -> None:
        if source_rate != self._source_rate:
            self.flush()
            self._source_rate = source_rate
            self._stream = None if source_rate == self.rate else soxr.ResampleStream(
                source_rate, self.rate, 1, dtype="float32", quality=RESAMPLE_QUALITY)
        self.samples.append(mono if self._stream is None else self._stream.resample_chunk(mono))

    def flush(self) -> None:
        """Release the samples the resampler still holds (its filter's delay): the end of an utterance."""
        if self._stream is not None:
            self.samples.append(self._stream.resample_chunk(np.zeros(0, np.float32), last=True))
        self._stream, self._source_rate = None, None

    def clear(self) -> None:
        """Drop everything queued and the resampler's state (barge-in)."""
        self.samples.clear()
        self._stream, self._source_rate = None, None

