"""A live session's streaming translator: the bundle's `translator_stream` graph fed the session's timeline a frame
at a time, its state carried from call to call (docs/live.md, "Streaming translators").

The graph's contract: `audio` [B, n, F] (the next n stream frames of F samples), `state` [B, S], `keep` [1] (how many
of the n frames are committed; the rest is provisional: lookahead not yet arrived, zero-filled) -> per-frame outputs
[B, n, ...] of stream frames [P - delay, P - delay + n) (P: frames committed before the call), `state_out` [B, S]
(the state after the committed frames) and `delay_frames` [1]. A stream starts from the rest state, the state
after a second of silence: what the windowed graph sees before a session's first audio.

A row is final once every frame it reads is committed (row j: frames up to j + delay); rows that read provisional
frames serve the frame that needs them now and are recomputed later. A rig whose frames are not the stream's (a
30 fps avatar on the 25 fps voice) takes each frame's parameters at its centre, interpolated between the two
nearest stream rows.

`StreamJob` separates planning a call from running it, so a pool can run one call for every session with a frame
due (`run_stream_jobs`: jobs of the same shape are stacked on the batch axis).

A stream whose graph has a steady form (the speaker's own translator) runs it while the window's loudness holds:
the streaming graph makes the last frames' features again with the window's newest statistics, which matters only
where they moved, at an utterance's start or end (docs/live.md, "The speaker's own translator").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

# Frames of silence fed from an all-zero state to reach the rest state; more than any stream's reach (the voice
# network sees 1 s = 25 frames back), so the rest state no longer depends on where it started.
REST_FRAMES = 32

# Frames of the translator stream's window (1 s of context and 160 ms of lookahead at 25 fps), whose mean power is the
# window's loudness, and the committed frames a refreshing call makes again. A call runs the refreshing graph where
# the window's loudness now is LOUDNESS_RATIO times, or a LOUDNESS_RATIO-th of, the loudness any of those frames'
# features were made at, and the steady graph elsewhere (measured on unseen speech in docs/live.md).
LOUDNESS_WINDOW_FRAMES = 29
REFRESHED_FRAMES = 4
LOUDNESS_RATIO = 2.0

# A call's stacked states at most this many bytes: past it a call costs more a session, not less (the states and
# each layer's activations leave the CPU's caches), while each call has a fixed cost that a served pool pays several
# times over (docs/live.md, "Sessions batched together"). A pool splits a bigger group into the fewest calls within
# it, of equal size: 36 of the demo speaker's 116 kB states a call; the voice's 16 kB states are split past 258.
MAX_CALL_STATE_BYTES = 4 << 20

# (audio [B, n, F], state, keep, refresh) -> outputs; called with graphs=(refreshing, steady) for a stream other than
# the driver's main one (StreamSpec.graphs)
RunStream = Callable[..., dict]
RowsOf = Callable[[dict], np.ndarray]  # graph outputs -> rows [B, n, D]


@dataclass(frozen=True)
class StreamSpec:
    """What a streaming graph says of itself, read once from its rest-state call."""

    delay: int  # frames a row lags the audio it is fed
    frame_samples: int  # F: samples of one stream frame
    rest_state: np.ndarray  # [S]
    rest_row: np.ndarray  # [D]: a row of silence (what rows before a stream's start are)
    steady: bool = False  # the graph has a steady form (calls with refresh=False)
    pads_exactly: bool = False  # frames appended to a call change none of its rows nor its state (`pads_exactly`)
    graphs: tuple[str, str] | None = None  # (refreshing, steady) graph names; None: the driver's main stream

    def delay_ms(self, sample_rate: int) -> float:
        """How far a row lags the audio it is fed, in ms, for audio at `sample_rate` (the driver's)."""
        return 1000.0 * self.delay * self.frame_samples / sample_rate


def stream_runner(run: RunStream, graphs: tuple[str, str] | None) -> RunStream:
    """`run` bound to a stream's graphs (`StreamSpec.graphs`; None: the driver's main stream, called as it is)."""
    if graphs is None:
        return run
    return lambda audio, state, keep, refresh=True: run(audio, state, keep, refresh, graphs=graphs)


def read_stream_spec(run: RunStream, rows_of: RowsOf, state_size: int, frame_samples: int,
                     steady: bool = False, graphs: tuple[str, str] | None = None) -> StreamSpec:
    """Feed REST_FRAMES frames of silence from an all-zero state: the rest state, the silent row and the delay
    (`graphs`: the stream's graphs where it is not the driver's main one)."""
    run = stream_runner(run, graphs)
    zeros = np.zeros((1, REST_FRAMES, frame_samples), np.float32)
    out = run(zeros, np.zeros((1, state_size), np.float32), REST_FRAMES, True)
    delay = int(np.asarray(out["delay_frames"]).reshape(-1)[0])
    if not 0 <= delay < REST_FRAMES:
        raise ValueError(f"the streaming graph says its rows lag {delay} frames; expected 0..{REST_FRAMES - 1}")
    rows = rows_of(out)
    rest_state = out["state_out"][0].astype(np.float32)
    return StreamSpec(delay, frame_samples, rest_state, rows[0, -1].astype(np.float32), steady,
                      pads_exactly(run, rows_of, rest_state, frame_samples), graphs)


# How far a padded call's rows and state may lie from the unpadded call's for `pads_exactly` (float32 rounding of
# kernels run on another shape: the voice graph measured 3e-8; a graph that reads the call's later frames, such as
# the speaker's own translator normalising over the call, moved them by 0.06-0.4).
PAD_TOLERANCE = 1e-5


def pads_exactly(run: RunStream, rows_of: RowsOf, rest_state: np.ndarray, frame_samples: int) -> bool:
    """Whether zero frames appended to a call change none of its rows nor its state (every row reads only the
    frames up to its own plus the delay), measured on a probe of noise: such a graph's calls of different lengths
    can be stacked into one, the shorter ones padded with zeros (`run_stream_jobs`)."""
    probe = (np.random.default_rng(0).standard_normal((1, 3, frame_samples)) * 0.1).astype(np.float32)
    state = rest_state[None]
    short = run(probe, state, 2, True)
    padded = run(np.concatenate([probe, np.zeros_like(probe)], axis=1), state, 2, True)
    rows_short, rows_padded = rows_of(short), rows_of(padded)[:, :probe.shape[1]]
    return bool(np.allclose(rows_short, rows_padded, rtol=PAD_TOLERANCE, atol=PAD_TOLERANCE)
                and np.allclose(short["state_out"], padded["state_out"], rtol=PAD_TOLERANCE, atol=PAD_TOLERANCE))


def frame_power(audio: np.ndarray) -> np.ndarray:
    """Mean square of each frame of `audio` [n, F] -> [n] (float64)."""
    # the sum over the count is what np.mean computes, bit for bit, without its per-call bookkeeping (a call a frame);
    # the float64 copy squared in place costs a third less than np.square's casting loop, with the same products
    values = audio.astype(np.float64)
    np.multiply(values, values, out=values)
    return np.add.reduce(values, axis=1) / audio.shape[1]


def window_loudness(powers: np.ndarray) -> np.float64:
    """The window's loudness: the mean of the last LOUDNESS_WINDOW_FRAMES frames' mean squares of `powers` (silence
    before the first counts as zeros)."""
    window = powers[-LOUDNESS_WINDOW_FRAMES:]
    if window.shape[0] < LOUDNESS_WINDOW_FRAMES:
        window = np.concatenate([np.zeros(LOUDNESS_WINDOW_FRAMES - window.shape[0]), window])
    # np.mean's own sum, bit for bit, over the same contiguous values as a pool's table sums a row of
    return np.add.reduce(window) / LOUDNESS_WINDOW_FRAMES


def loudness_moved(now: float, made: np.ndarray) -> bool:
    """Whether a call needs the refreshing graph: the window's loudness `now` is LOUDNESS_RATIO times, or a
    LOUDNESS_RATIO-th of, the loudness at which any of the last REFRESHED_FRAMES committed frames' features were
    made (`made`; the rest state's: zeros), so they would be made again at the newest statistics."""
    return bool(now > LOUDNESS_RATIO * made.min() or made.max() > LOUDNESS_RATIO * now)


def made_after(made: np.ndarray, keep: int, refreshed: bool, now: float) -> np.ndarray:
    """`made` after a call at loudness `now` that committed `keep` frames: a refreshing call made the last
    REFRESHED_FRAMES again, and every call makes its committed frames, at `now` (a call that commits none leaves
    the state's features as they were)."""
    if keep <= 0:
        return made
    if refreshed or keep >= REFRESHED_FRAMES:
        return np.full(REFRESHED_FRAMES, now)
    return np.concatenate([made[keep:], np.full(keep, now)])


@dataclass
class StreamJob:
    """One planned call of one session's stream: `audio` [n, F] from its committed position, `keep` frames to
    commit. `rows` [n, D] and `state` (after the committed frames) are filled by `run_stream_jobs`."""

    stream: TranslatorStream
    audio: np.ndarray
    keep: int
    refresh: bool = True  # False: the graph's steady form
    powers: np.ndarray | None = None  # each frame's mean square (a stream with a steady form: its gate reads them)
    loudness: float = 0.0  # the window's loudness at this call (`window_loudness`; a stream with a steady form)
    rows: np.ndarray | None = None
    state: np.ndarray | None = None
    state_row: tuple[np.ndarray, int] | None = None  # (the call's state_out, this job's row of it)

    @property
    def shape(self) -> tuple[int, int, bool]:
        return self.audio.shape[0], self.keep, self.refresh


def sessions_per_call(state_size: int) -> int:
    """The most sessions one call stacks, for a stream whose state holds `state_size` floats."""
    return max(1, MAX_CALL_STATE_BYTES // (4 * max(1, int(state_size))))


def run_stream_jobs(jobs: Sequence[StreamJob], run: RunStream, rows_of: RowsOf) -> list[int]:
    """Run every job: one graph call per distinct (stream, frames, keep, refresh), the sessions stacked on the batch
    axis (at most `sessions_per_call` of them a call, a bigger group split evenly); a graph that pads exactly stacks
    jobs of different lengths into one call per (stream, keep, refresh), the shorter ones zero-padded at the end.
    Returns the sessions of each call."""
    groups: dict[tuple[tuple[str, str] | None, int, int, bool], list[StreamJob]] = {}
    for job in jobs:
        frames, keep, refresh = job.shape
        spec = job.stream.spec
        groups.setdefault((spec.graphs, -1 if spec.pads_exactly else frames, keep, refresh), []).append(job)
    calls = []
    for (graphs, _, keep, refresh), group in groups.items():
        call = stream_runner(run, graphs)
        for lo, hi in call_bounds(len(group), sessions_per_call(group[0].stream.state.shape[0])):
            part = group[lo:hi]
            frames = max(job.audio.shape[0] for job in part)
            audio = np.zeros((len(part), frames, part[0].audio.shape[1]), np.float32)
            for k, job in enumerate(part):
                audio[k, :job.audio.shape[0]] = job.audio
            out = call(audio, _stacked_states(part), keep, refresh)
            rows, states = rows_of(out), out["state_out"]
            for k, job in enumerate(part):
                job.rows, job.state, job.state_row = rows[k, :job.audio.shape[0]], states[k], (states, k)
            calls.append(len(part))
    return calls


def call_bounds(count: int, most: int) -> list[tuple[int, int]]:
    """[lo, hi) of each call that `count` stacked sessions are cut into: the fewest calls of at most `most`, their
    sizes differing by one at most (37 in calls of 36: 19 and 18, not 36 and 1, whose call of one would pay a call's
    fixed cost alone); none for no sessions."""
    if count <= 0:
        return []
    calls = -(-count // max(1, most))
    size, extra = divmod(count, calls)
    edges = [k * size + min(k, extra) for k in range(calls + 1)]
    return list(zip(edges, edges[1:], strict=False))


def _stacked_states(jobs: Sequence[StreamJob]) -> np.ndarray:
    """The jobs' states as one [B, S] array: the last call's state_out itself when the jobs are that call's sessions
    in its order (each state still its row there: a pool's sessions due together tick after tick), else a copy."""
    last = jobs[0].stream.state_row
    if last is not None and last[0].shape[0] == len(jobs) and all(
            job.stream.state_row is not None and job.stream.state_row[0] is last[0] and job.stream.state_row[1] == k
            for k, job in enumerate(jobs)):
        return last[0]
    return np.stack([job.stream.state for job in jobs])


def _trailing_silence(samples: np.ndarray) -> int:
    """How many zeros end `samples` (all of them when nothing is spoken)."""
    if samples.shape[0] == 0:
        return 0
    spoken = samples[::-1] != 0  # from the end: the first nonzero's offset is the silence (argmax: no index array)
    last = int(spoken.argmax())
    return last if spoken[last] else samples.shape[0]


class TranslatorStream:
    """One session's stream over its timeline (speech-rate samples): `offer` what is known of the timeline,
    `plan` the call that the next rig frames need, `finish` with its results, then read `params`."""

    def __init__(self, spec: StreamSpec, rig_samples_per_frame: float) -> None:
        self.spec = spec
        self.rig_spf = float(rig_samples_per_frame)
        self.aligned = math.isclose(self.rig_spf, spec.frame_samples)  # rig frames are stream frames
        self.reset(0)

    def reset(self, position: int) -> None:
        """Restart from the rest state with stream frame 0 at timeline sample `position` (a session's start, a
        barge-in: what the windowed path's cleared context is)."""
        self.origin = int(position)
        self.state = self.spec.rest_state.copy()
        self.state_row: tuple[np.ndarray, int] | None = None  # (a call's state_out, the row `state` is), as finished
        self.committed = 0  # stream frames in the state
        self.known = np.zeros(0, np.float32)  # timeline samples from the committed position on, as far as known
        self.final: dict[int, np.ndarray] = {}  # stream frame -> its final row
        self.quiet = REST_FRAMES * self.spec.frame_samples  # silent samples at the end of what was committed
        self._provisional: dict[int, np.ndarray] = {}
        self._powers = np.zeros(0)  # the committed frames' mean squares, the last window's (rest: silence)
        self._made = np.zeros(REFRESHED_FRAMES)  # the loudness its last frames were made at (`loudness_moved`)
        self._at_rest = True  # nothing offered nor run since this reset: all of the above is as it set it

    @property
    def known_end(self) -> int:
        """The timeline sample up to which the stream knows the audio."""
        return self.origin + self.committed * self.spec.frame_samples + self.known.shape[0]

    def offer(self, start: int, samples: np.ndarray) -> None:
        """Timeline samples [start, start + len) are known (queued speech, its lookahead): the stream keeps those
        past what it already holds."""
        end = self.known_end
        if start > end:  # a gap nobody offered is silence
            self.offer(end, np.zeros(start - end, np.float32))
            end = start
        new = samples[end - start:]
        if new.shape[0]:
            self.known = np.concatenate([self.known, new.astype(np.float32, copy=False)])
            self._at_rest = False

    def idle(self, start: int, stop: int) -> None:
        """Timeline samples [start, stop) are an idle gap (silence), every frame before it made. Once a second of
        silence ends what the stream knows, it restarts at rest at `stop` instead (the state after that much
        silence is the rest state), so an idle session holds and computes nothing."""
        if self._at_rest and start >= self.origin:  # still at rest: the reset below would change the origin only
            self.origin = int(stop)
            return
        self.offer(start, np.zeros(0, np.float32))
        silent = _trailing_silence(self.known)
        if silent == self.known.shape[0]:  # nothing spoken since the committed audio's own silent end
            silent += self.quiet
        if silent + stop - max(start, self.known_end) >= REST_FRAMES * self.spec.frame_samples:
            self.reset(stop)  # every frame before the gap is made: what the stream still knew of it is not needed
        else:
            self.offer(start, np.zeros(stop - start, np.float32))

    def _centre(self, frame: int) -> float:
        """Rig frame `frame`'s centre on the stream's row grid (row j's centre at j)."""
        return (frame * self.rig_spf + self.rig_spf / 2 - self.origin) / self.spec.frame_samples - 0.5

    def _span(self, frame: int) -> tuple[int, int]:
        """(first, last) stream frames whose rows rig frame `frame` reads."""
        if self.aligned:
            index = int(round((frame * self.rig_spf - self.origin) / self.spec.frame_samples))
            return index, index
        first = math.floor(self._centre(frame))
        return first, first + 1

    def plan(self, frames: range) -> StreamJob | None:
        """The call rig frames `frames` still need (None: their rows are final already): every known whole frame
        committed, the frames after them provisional (the known samples, then zeros)."""
        last = self._span(frames[-1])[1]  # the last stream frame whose row the frames read
        if last < 0 or last in self.final:  # rows become final in order: the rest are final too, or every row is
            if all(self._has_final(j) for f in frames for j in self._span(f)):
                return None
        size = self.spec.frame_samples
        count = max(last + self.spec.delay + 1 - self.committed, 1)  # stream frames to the last row's reach
        known = self.known.shape[0]
        keep = min(known // size, count)
        if known >= count * size:  # the usual case: every frame is known (`known` is never written in place)
            audio = self.known[:count * size].reshape(count, size)
        else:
            audio = np.zeros((count, size), np.float32)
            audio.reshape(-1)[:known] = self.known
        if not self.spec.steady:  # one graph: no gate, nothing to measure
            return StreamJob(self, audio, keep)
        powers = frame_power(audio)
        now = window_loudness(np.concatenate([self._powers, powers]))
        return StreamJob(self, audio, keep, loudness_moved(now, self._made), powers, now)

    def _has_final(self, index: int) -> bool:
        return index < 0 or index in self.final

    def finish(self, job: StreamJob) -> None:
        """Take a run job's rows and state: committed frames leave `known`, final rows are kept."""
        size, first = self.spec.frame_samples, self.committed - self.spec.delay
        final_end = self.committed + job.keep - self.spec.delay  # rows before it read committed frames only
        self._provisional = {}
        for k, row in enumerate(job.rows):
            index = first + k
            (self.final if index < final_end else self._provisional)[index] = row
        if job.powers is not None:  # the gate's history: the committed frames' mean squares, the last window's
            self._powers = np.concatenate([self._powers, job.powers[:job.keep]])[-LOUDNESS_WINDOW_FRAMES:]
            self._made = made_after(self._made, job.keep, job.refresh, job.loudness)
        committed = job.audio[:job.keep].reshape(-1)
        silent = _trailing_silence(committed)
        self.quiet = self.quiet + silent if silent == committed.shape[0] else silent
        self.state = np.asarray(job.state, np.float32)
        self.state_row = job.state_row
        self.committed += job.keep
        self._at_rest = False
        self.known = self.known[job.keep * size:]

    @property
    def powers(self) -> np.ndarray:
        """The committed frames' mean squares that the loudness gate reads (the last window's at most)."""
        return self._powers

    @property
    def made(self) -> np.ndarray:
        """The loudness at which the last REFRESHED_FRAMES committed frames' features were made (`loudness_moved`)."""
        return self._made

    def resume(self, committed: int, state: np.ndarray, state_row: tuple[np.ndarray, int] | None, quiet: int,
               powers: np.ndarray, made: np.ndarray, final: dict[int, np.ndarray], known: np.ndarray) -> None:
        """Take up the stream as a pool that ran its calls elsewhere left it (runtime/live_steady.py): what `finish`
        would have left after its last call, which committed every frame it made (no provisional rows)."""
        self.committed, self.state, self.state_row, self.quiet = committed, state, state_row, quiet
        self._powers, self._made, self.final, self.known = powers, made, final, known
        self._provisional, self._at_rest = {}, False

    def _row(self, index: int) -> np.ndarray:
        if index < 0:
            return self.spec.rest_row
        row = self.final.get(index)
        return row if row is not None else self._provisional[index]

    def params(self, frame: int) -> np.ndarray:
        """Rig frame `frame`'s parameters [D] from the rows planned and run for it; older rows are dropped."""
        first, last = self._span(frame)
        if first == last:
            value = self._row(first)
        else:
            weight = np.float32(self._centre(frame) - first)
            value = (1 - weight) * self._row(first) + weight * self._row(last)
        for index in [i for i in self.final if i < first]:
            del self.final[index]
        return value


__all__ = ["MAX_CALL_STATE_BYTES", "REST_FRAMES", "StreamJob", "StreamSpec", "TranslatorStream", "call_bounds",
           "frame_power", "loudness_moved", "made_after", "read_stream_spec", "run_stream_jobs", "sessions_per_call",
           "stream_runner", "window_loudness"]
