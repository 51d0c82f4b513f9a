"""A pool's steady frames made together: the paced streaming sessions whose next frame is steady are rows of one
table, and a tick plans all their frames with numpy across the rows (docs/live.md, "Steady frames made together").

A steady frame is the usual one mid-utterance: the voice arriving as it is spoken, exactly this frame's audio and
lookahead are in, and the stream's call commits one frame whose row is this frame's. `LiveSession` makes it through
some 260 Python calls (its queues, the silence gate's sums over the frame and its lookahead, the stream's offer, plan
and finish); at a hundred sessions that is a third of a live server's CPU. Here a session's gate (the last frames'
sums) and stream (its committed count, the trailing silence, the loudness gate's powers, its state as a row of the
call that made it) live in the table's arrays while its frames are steady: each frame's sums are made once, when it
arrives as the newest lookahead frame, and the gains, the gate's running totals and the loudness test are numpy
across the rows. The frame itself is made with the tick's others by `live_rows.make_rows` (or alone by
`LiveSession.make_frame`).

A session enters the table on a steady frame and leaves it, its gate and stream written back into its objects, on
any other (an utterance's start or end, a late, deferred or batched frame, a barge-in); those frames are its own.
So every frame is the one `stream_job` and `step` make, bit for bit (tests/test_live_steady.py): the sums are the
same reductions (`frame_sums`, `frame_power`), added in the same order, and the jobs are stacked with the other
sessions' in the same calls.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from .live import GATE_REBUILD, FramePlan, LiveFrame, LiveSession, SteadyState, SteadyTake, frame_sums
from .translate import silence_gain_of_sums
from .translate_stream import LOUDNESS_RATIO, LOUDNESS_WINDOW_FRAMES, REFRESHED_FRAMES, StreamJob, run_stream_jobs

_POWERS = LOUDNESS_WINDOW_FRAMES  # the loudness gate's powers: its window's


@dataclass
class _RowStream:
    """What `run_stream_jobs` reads of a job's stream, for a session whose stream lives in the table."""

    spec: object
    state: np.ndarray
    state_row: tuple[np.ndarray, int] | None


@dataclass
class SteadyFrame:
    """A session's steady frame planned by `SteadyFrames.plan`: its `job` to run with the other sessions' (by
    `run_stream_jobs`), then `SteadyFrames.take` gives its plan."""

    live: LiveSession
    table: SteadyTable
    row: int
    job: StreamJob
    taken: SteadyTake
    gain: float

    @property
    def interrupts(self) -> int:
        """The frame's epoch on the wire (the session's barge-ins when it was planned)."""
        return self.taken.interrupts


class SteadyTable:
    """The rows of the sessions of one `LiveSession.steady_key` whose frames are steady now."""

    def __init__(self, live: LiveSession, spec) -> None:
        self.spec, self.frame = spec, spec.frame_samples
        self.lookahead, self.context, self.delay = live.lookahead_frames, live.context_frames, spec.delay
        self.gate_dbfs = live.driver.silence_gate_dbfs
        self._row_of: dict[LiveSession, int] = {}  # a session in the table -> its row
        self._free: list[int] = []
        self.new_frames = self.call_frames = np.zeros((0, self.frame), np.float32)
        self._grow(16)

    def _grow(self, rows: int) -> None:
        """Room for `rows` sessions (the arrays keep their rows)."""
        held = len(getattr(self, "streams", []))
        width, ahead = self.context, self.lookahead + 1

        def grown(name: str, shape: tuple, dtype) -> np.ndarray:
            out = np.zeros((rows, *shape), dtype)
            if held:
                out[:held] = getattr(self, name)
            return out

        self.gate_n = grown("gate_n", (width,), np.int64)  # each past frame's samples,
        self.gate_t = grown("gate_t", (width,), np.float64)  # sum
        self.gate_q = grown("gate_q", (width,), np.float64)  # and sum of squares (a ring)
        self.gate_pos = grown("gate_pos", (), np.int64)  # the ring's oldest frame
        self.gate_count = grown("gate_count", (), np.int64)
        self.gate_total = grown("gate_total", (), np.float64)
        self.gate_squares = grown("gate_squares", (), np.float64)
        self.gate_pushes = grown("gate_pushes", (), np.int64)
        self.ahead_t = grown("ahead_t", (ahead,), np.float64)  # sums of the next frame and its
        self.ahead_q = grown("ahead_q", (ahead,), np.float64)  # lookahead, newest last
        self.powers = grown("powers", (_POWERS,), np.float64)  # the committed frames' powers
        self.made = grown("made", (REFRESHED_FRAMES,), np.float64)  # the loudness their features were made at
        self.committed = grown("committed", (), np.int64)  # the stream's committed frames
        self.quiet = grown("quiet", (), np.int64)  # and the silence ending them
        self.epoch = grown("epoch", (), np.int64)  # the session's epoch when it entered
        more = rows - held
        self.streams: list = getattr(self, "streams", []) + [None] * more  # what a row's jobs say of its state
        self.last_rows: list = getattr(self, "last_rows", []) + [None] * more  # (stream row index, its values)
        self._free.extend(range(rows - 1, held - 1, -1))

    def __len__(self) -> int:
        return len(self._row_of)

    def row_of(self, live: LiveSession) -> int | None:
        return self._row_of.get(live)

    def entered(self, row: int | None) -> int | None:
        """The epoch at which the session of `row` entered (None: no row)."""
        return None if row is None else int(self.epoch[row])

    def scratch(self, count: int) -> None:
        """`new_frames` and `call_frames` of at least `count` rows, kept from tick to tick (fresh pages cost more
        than the sums here)."""
        if self.new_frames.shape[0] < count:
            self.new_frames = np.zeros((count, self.frame), np.float32)
            self.call_frames = np.zeros((count, self.frame), np.float32)

    def enter(self, live: LiveSession, entry: SteadyState, epoch: int) -> int:
        """A row for the session, its gate and stream as `entry` (`LiveSession.take_steady`'s) gives them."""
        if not self._free:
            self._grow(2 * len(self.streams))
        row = self._free.pop()
        self._row_of[live] = row
        if self.context:
            entries = np.array(entry.gate, np.float64).reshape(self.context, 3)
            self.gate_n[row], self.gate_t[row], self.gate_q[row] = entries[:, 0], entries[:, 1], entries[:, 2]
        self.gate_pos[row], self.gate_count[row] = 0, entry.count
        self.gate_total[row], self.gate_squares[row], self.gate_pushes[row] = entry.total, entry.squares, entry.pushes
        # this frame's and its lookahead's sums but the newest's
        self.ahead_t[row, :self.lookahead], self.ahead_q[row, :self.lookahead] = frame_sums(entry.ahead)
        powers = entry.powers[-_POWERS:]
        self.powers[row] = 0.0
        self.powers[row, _POWERS - powers.shape[0]:] = powers  # silence before counts as zeros (`window_loudness`)
        self.made[row] = entry.made
        self.committed[row], self.quiet[row], self.epoch[row] = entry.committed, entry.quiet, epoch
        self.streams[row] = _RowStream(self.spec, entry.state, entry.state_row)
        self.last_rows[row] = None
        return row

    def leave(self, live: LiveSession, row: int) -> None:
        """The session's gate and stream given back to it (`LiveSession.leave_steady`), its row freed."""
        del self._row_of[live]
        self._free.append(row)
        order = (np.arange(self.context) + self.gate_pos[row]) % self.context if self.context else []
        gate = list(zip(self.gate_n[row, order].tolist(), self.gate_t[row, order].tolist(),
                        self.gate_q[row, order].tolist(), strict=True)) if self.context else []
        stream = self.streams[row]
        live.leave_steady(int(self.epoch[row]), SteadyState(
            gate, int(self.gate_count[row]), float(self.gate_total[row]), float(self.gate_squares[row]),
            int(self.gate_pushes[row]), self.powers[row].copy(), self.made[row].copy(), int(self.committed[row]),
            int(self.quiet[row]), stream.state, stream.state_row,
            final=None if self.last_rows[row] is None else dict([self.last_rows[row]])))

    def plan(self, rows_planned: list[int], new: np.ndarray, call: np.ndarray) -> list[float]:
        """The gains of planned rows' frames and their gate and stream state moved on by a frame, numpy across the
        rows: rows `rows_planned` whose newest lookahead frames are `new` [R, F] and whose calls' frames are `call`
        [R, F]. Returns each frame's gain and sets the loudness test of each in `self.refresh`."""
        rows = np.asarray(rows_planned, np.int64)
        size, lookahead = self.frame, self.lookahead
        new_t, new_q = frame_sums(new)  # the newest frame's sums (the same reduction a row as the session's)
        ahead_t, ahead_q = self.ahead_t[rows], self.ahead_q[rows]
        ahead_t[:, lookahead], ahead_q[:, lookahead] = new_t, new_q
        # the gain over the past frames and this frame and its lookahead, added a frame at a time (`_GateHistory`)
        count = self.gate_count[rows] + (lookahead + 1) * size
        total, squares = self.gate_total[rows], self.gate_squares[rows]
        for j in range(lookahead + 1):
            total, squares = total + ahead_t[:, j], squares + ahead_q[:, j]
        gains = [silence_gain_of_sums(t, q, c, self.gate_dbfs)
                 for t, q, c in zip(total.tolist(), squares.tolist(), count.tolist(), strict=True)]
        if self.context:  # this frame joins the gate's ring, the oldest leaves (`_GateHistory.push`)
            position = self.gate_pos[rows]
            old_n, old_t, old_q = (a[rows, position] for a in (self.gate_n, self.gate_t, self.gate_q))
            self.gate_n[rows, position], self.gate_t[rows, position] = size, ahead_t[:, 0]
            self.gate_q[rows, position] = ahead_q[:, 0]
            self.gate_count[rows] = self.gate_count[rows] + size - old_n
            self.gate_total[rows] = self.gate_total[rows] + ahead_t[:, 0] - old_t
            self.gate_squares[rows] = self.gate_squares[rows] + ahead_q[:, 0] - old_q
            self.gate_pos[rows] = (position + 1) % self.context
            pushes = self.gate_pushes[rows] + 1
            self.gate_pushes[rows] = pushes
            for row in rows[pushes % GATE_REBUILD == 0].tolist():  # in the ring's order, oldest first
                order = (np.arange(self.context) + self.gate_pos[row]) % self.context
                self.gate_total[row] = sum(self.gate_t[row, order].tolist())
                self.gate_squares[row] = sum(self.gate_q[row, order].tolist())
        self.ahead_t[rows, :lookahead], self.ahead_q[rows, :lookahead] = ahead_t[:, 1:], ahead_q[:, 1:]
        # the call's frame commits: its power joins the loudness gate's, its trailing zeros the stream's silence
        if self.spec.steady:
            powers = self.powers[rows]
            powers[:, :-1] = powers[:, 1:]
            powers[:, -1] = ahead_q[:, self.delay] / size  # `frame_power`
            self.powers[rows] = powers
            now = np.add.reduce(powers, axis=1) / LOUDNESS_WINDOW_FRAMES  # `window_loudness`, a row at a time
            made = self.made[rows]
            refresh = (now > LOUDNESS_RATIO * made.min(axis=1)) | (made.max(axis=1) > LOUDNESS_RATIO * now)
            made[:, :-1] = made[:, 1:]  # `made_after`: the frame made at `now`, and a refresh's frames again
            made[:, -1] = now
            made[refresh] = now[refresh, None]
            self.made[rows] = made
            self.refresh = refresh.tolist()
        else:
            self.refresh = [True] * len(rows_planned)
        spoken = call != 0
        silent = np.where(spoken.any(axis=1), np.argmax(spoken[:, ::-1], axis=1), size)
        self.quiet[rows] = np.where(silent == size, self.quiet[rows] + silent, silent)
        self.committed[rows] += 1
        return gains


class SteadyFrames:
    """The steady frames of a pool's sessions: `plan` those due now (the others are left to `stream_job` and
    `next_plan`), run their jobs with the others', then `take` each one's plan (or `make` its frame). One pool thread
    uses it; the sessions' producers push, flush and interrupt from any thread, under each session's lock as ever."""

    def __init__(self) -> None:
        self._tables: dict[tuple, SteadyTable] = {}
        self._keys: weakref.WeakKeyDictionary[LiveSession, tuple | None] = weakref.WeakKeyDictionary()

    def __len__(self) -> int:
        return sum(len(table) for table in self._tables.values())

    def plan(self, lives: list[LiveSession], now: float) -> list[SteadyFrame | None]:
        """Each session's steady frame due by `now`, planned (its queues taken, its job made), or None: its frame, if
        any, is its own (`stream_job`, `next_plan`). A session in the table whose frame is not steady leaves it."""
        out: list[SteadyFrame | None] = [None] * len(lives)
        picked: dict[int, tuple[SteadyTable, list]] = {}
        keys = self._keys
        for position, live in enumerate(lives):
            key = keys.get(live, False)
            if key is False:
                key = keys[live] = live.steady_key()
            if key is None:
                continue
            table = self._tables.get(key)
            if table is None:
                table = self._tables[key] = SteadyTable(live, live.stream_spec)
            if id(table) not in picked:
                picked[id(table)] = (table, [])
                table.scratch(len(lives))
            items = picked[id(table)][1]
            row, k = table.row_of(live), len(items)
            taken = live.take_steady(now, table.entered(row), table.new_frames[k], table.call_frames[k])
            if taken is None:
                if row is not None:
                    table.leave(live, row)
                continue
            if row is None:
                row = table.enter(live, taken.entry, taken.epoch)
            items.append((position, live, row, taken))
        for table, items in picked.values():
            if not items:
                continue
            count = len(items)
            gains = table.plan([item[2] for item in items], table.new_frames[:count], table.call_frames[:count])
            for k, (position, live, row, taken) in enumerate(items):
                # the job's audio a view: run_stream_jobs copies it into the call's before the next plan writes here
                job = StreamJob(table.streams[row], table.call_frames[k:k + 1], 1, table.refresh[k])
                out[position] = SteadyFrame(live, table, row, job, taken, gains[k])
        return out

    def take(self, planned: SteadyFrame) -> tuple[FramePlan, float] | None:
        """The planned frame's plan and due time, its job run (as `LiveSession.next_plan` gives them: the frame is
        then made by `make_frame`, or with others by `live_rows.make_rows`); None when the session was closed or
        barged in on since it was planned (it left the table: `next_plan` then ends it, or makes its idle frame)."""
        live, table, row, job = planned.live, planned.table, planned.row, planned.job
        if job.rows is None:  # the calls together failed: alone it raises its own error, which stops the session
            try:
                run_stream_jobs([job], live.driver.run_stream, live.driver.stream_rows)
            except Exception as error:
                live.fail(error)
                raise
        plan = live.steady_plan(planned.taken.epoch, job.rows[0] * np.float32(planned.gain), planned.taken.out_audio)
        if plan is None:
            if table.row_of(live) is not None:
                table.leave(live, row)
            return None
        row_stream = table.streams[row]
        row_stream.state, row_stream.state_row = job.state, job.state_row
        table.last_rows[row] = (int(table.committed[row]) - 1 - table.delay, job.rows[0])
        return plan, planned.taken.due

    def make(self, planned: SteadyFrame) -> LiveFrame | None:
        """The planned frame made alone (`take`, then the session's `make_frame`); None as `take` says."""
        taken = self.take(planned)
        if taken is None:
            return None
        frame = planned.live.make_frame(taken[0])
        planned.live.keep_pace(taken[1])
        return frame

    def forget(self, live: LiveSession) -> None:
        """A session the pool let go of: its row is freed."""
        for table in self._tables.values():
            row = table.row_of(live)
            if row is not None:
                table.leave(live, row)


__all__ = ["SteadyFrame", "SteadyFrames", "SteadyTable"]
