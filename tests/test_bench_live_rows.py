"""`gt-bench live-clients`' translator rows per speaking session-second and its pool threads' CPU by part
(tools/bench/live_clients.py `translator_rows_of`, `round_rows`, `pool_cpu_of`, `round_pool_cpu`): read from the
/metrics body gt-serve writes (serve/metrics.py), so the bench and the server agree on the counters' names and
labels."""

from __future__ import annotations

import pytest

from gaussiantalker.serve.metrics import ServeMetrics
from tools.bench.live_clients import (
    _pool,
    _pooled_pool_cpu,
    _pooled_rows,
    _rows,
    pool_cpu_of,
    round_pool_cpu,
    round_rows,
    translator_rows_of,
)


def _exposition(committed: int, provisional: int, pool_cpu: tuple[float, float] | None = None) -> str:
    """A /metrics body with these rows and, given, the pool's CPU (translator, frames); another counter besides."""
    metrics = ServeMetrics()
    metrics.translator_rows.labels(kind="committed").inc(committed)
    metrics.translator_rows.labels(kind="provisional").inc(provisional)
    if pool_cpu is not None:
        metrics.pool_cpu.labels(part="translator").inc(pool_cpu[0])
        metrics.pool_cpu.labels(part="frames").inc(pool_cpu[1])
    metrics.frames.labels(mode="client-render").inc(7)  # another counter: neither rows nor CPU
    return metrics.exposition().decode()


def test_rows_are_read_from_the_servers_own_metrics():
    assert translator_rows_of(_exposition(250, 300)) == {"committed": 250.0, "provisional": 300.0}
    assert translator_rows_of(ServeMetrics().exposition().decode()) == {}  # nothing made yet: no sample


def test_a_round_counts_its_rows_over_the_seconds_its_voices_spoke():
    clients = [{"error": None, "answered": 10.0, "interrupt_sent": 14.0},
               {"error": None, "answered": 11.0, "interrupt_sent": 15.5},
               {"error": "refused", "answered": 11.0, "interrupt_sent": 13.0},  # a failed client spoke nothing
               {"error": None, "answered": 12.0}]  # never barged in (closed first): not counted
    before = translator_rows_of(_exposition(100, 20))
    after = translator_rows_of(_exposition(300, 230))
    rows = round_rows(before, after, clients)
    assert rows == {"committed": 200.0, "provisional": 210.0, "speaking_s": pytest.approx(8.5)}
    assert round_rows(None, after, clients)["committed"] == 300.0  # the first round: nothing counted before it
    assert round_rows(None, None, clients) is None  # a server that does not count rows (an older commit)
    assert _rows(rows) == "48.2 (24.7)" and _rows(None) == "–"
    assert _pooled_rows([{"translator_rows": rows}, {"translator_rows": rows}])["speaking_s"] == pytest.approx(17.0)
    assert _pooled_rows([{"translator_rows": rows}, {"translator_rows": None}]) is None


def test_a_round_splits_the_pools_cpu_into_its_translator_calls_and_the_rest():
    before, after = pool_cpu_of(_exposition(9, 0, (1.5, 0.5))), pool_cpu_of(_exposition(9, 0, (4.75, 2.0)))
    assert before == {"translator": 1.5, "frames": 0.5}
    assert pool_cpu_of(_exposition(9, 0)) == {}  # no tick counted yet: no sample (the rows are not read as CPU)
    spent = round_pool_cpu(before, after)
    assert spent == {"translator": 3.25, "frames": 1.5}
    assert round_pool_cpu(None, None) is None  # an older commit's server does not count it
    assert _pooled_pool_cpu([{"pool_cpu": spent}, {"pool_cpu": spent}]) == {"translator": 6.5, "frames": 3.0}
    assert _pooled_pool_cpu([{"pool_cpu": spent}, {"pool_cpu": None}]) is None
    # per session-second of the round's sessions, as the table shows it beside the server's CPU
    assert _pool({"pool_cpu": spent, "session_s": 500.0}) == "0.0065 / 0.0030"
    assert _pool({"pool_cpu": None, "session_s": 500.0}) == "–"
