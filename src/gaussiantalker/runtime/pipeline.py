"""Overlapping a frame loop's stages on threads, with bounded queues (docs/speed.md, "Pipelined frame loop").

A frame is deformation + depth sort, then the draw, then (when compositing) F and the blend, then (in
`write_video`) encoding. Each stage spends most of its time in code that releases the GIL (onnxruntime, numpy's
sort, the CPU splatter's numba kernels, PyAV's encoder), so on a machine with cores to spare the stages of
neighbouring frames can run at once instead of one after the other. Three pieces, each bounded so memory never
grows with the length of a clip, and each shutting its thread down when its consumer stops early or fails:

* `Ahead`: an iterator run on a worker thread, at most `depth` items ahead of its consumer.
* `in_order`: a function applied on worker threads (one, or several: whole frames at once) to items pulled on the
  caller's thread, results in order.
* `Sink`: a function (an encoder's `write`) called on a worker thread for each item handed to it, in order.

Errors raised on a worker come back to the consumer as the same exception object, at its next call.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")

# How often a worker blocked on a full queue looks whether its consumer has gone (seconds): only a stop waits on it.
_POLL_S = 0.05


class _Failure:
    """An exception raised on the worker, carried through the queue to the consumer."""

    def __init__(self, error: BaseException) -> None:
        self.error = error


_END = object()


class Ahead(Iterator[T], Generic[T]):
    """`source` iterated on a worker thread, at most `depth` items ahead of the consumer (a bounded queue).

    Items come out in the source's order; an exception the source raises is raised by the consumer's next `next`
    (the same object). `close()` (or leaving a `with` block, or the end of the items) stops the worker: it finishes
    the item it is computing, closes the source and exits; close returns once the thread has ended."""

    def __init__(self, source: Iterable[T], depth: int = 2, name: str = "gt-ahead") -> None:
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        self._source = source
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._done = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        """Queue `item`, waiting while the queue is full; False if the consumer stopped meanwhile."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        iterator = iter(self._source)
        try:
            for item in iterator:
                if not self._put(item):
                    return
            self._put(_END)
        except BaseException as error:  # noqa: BLE001  (handed to the consumer, which raises it)
            self._put(_Failure(error))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()

    def __iter__(self) -> Ahead[T]:
        return self

    def __next__(self) -> T:
        if self._done:
            raise StopIteration
        item = self._queue.get()
        if item is _END:
            self.close()
            raise StopIteration
        if isinstance(item, _Failure):
            self.close()
            raise item.error
        return item

    @property
    def alive(self) -> bool:
        """Whether the worker thread is still running."""
        return self._thread.is_alive()

    def close(self) -> None:
        """Stop the worker and wait for its thread to end (it finishes the item in hand first)."""
        self._done = True
        self._stop.set()
        while self._thread.is_alive():
            try:  # unblock a worker waiting on a full queue at once
                while True:
                    self._queue.get_nowait()
            except queue.Empty:
                pass
            self._thread.join(_POLL_S)

    def __enter__(self) -> Ahead[T]:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def in_order(function: Callable[..., R], items: Iterable[tuple], depth: int = 1,
             name: str = "gt-stage", *, workers: int = 1,
             initializer: Callable[[], object] | None = None) -> Iterator[R]:
    """`function(*item)` for each item, run on `workers` threads (each first calls `initializer`) while the
    caller's thread pulls (and so computes) the next items; results in the items' order, at most `depth` + 1 in
    flight. An exception from `function` is raised here, the same object; one from `items` too, after the results
    of the items before it. When the caller stops early, the calls not started are dropped and the threads end
    before this generator closes."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    pending: deque[Future] = deque()
    source = iter(items)
    failure: Exception | None = None
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name, initializer=initializer) as pool:
        try:
            while True:
                try:
                    item = next(source)
                except StopIteration:
                    break
                except Exception as error:  # noqa: BLE001  (raised below, after the items before it)
                    failure = error
                    break
                pending.append(pool.submit(function, *item))
                if len(pending) > depth:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()
    if failure is not None:
        raise failure


class Sink(Generic[T]):
    """`function(item)` called on a worker thread for each item `put`, in order, at most `depth` waiting: an
    encoder's `write` running while the next frame is made. An exception `function` raised is raised by the next
    `put` or by `finish` (the same object); the items after it are not passed to `function`. Use it in a `with`
    block: leaving it normally waits for every item to be written (`finish`), leaving on an error drops what is
    still queued; either way the thread has ended when the block is left."""

    def __init__(self, function: Callable[[T], object], depth: int = 2, name: str = "gt-sink") -> None:
        self._function = function
        self._depth = depth
        self._pending: deque[Future] = deque()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)

    def put(self, item: T) -> None:
        """Queue `item` (waiting while `depth` items are queued); raises an earlier call's exception."""
        while self._pending and (self._pending[0].done() or len(self._pending) >= self._depth):
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(self._function, item))

    def finish(self) -> None:
        """Wait until every queued item has been passed to `function`; raises its exception if one failed."""
        try:
            while self._pending:
                self._pending.popleft().result()
        finally:
            self.close()

    def close(self) -> None:
        """Drop the items not yet started and end the thread (after the item in hand)."""
        for future in self._pending:
            future.cancel()
        self._pending.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Sink[T]:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.finish()
        else:
            self.close()


__all__ = ["Ahead", "Sink", "in_order"]
