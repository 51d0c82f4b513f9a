"""`gt-bench live-clients`' split of the server's CPU into a base and a cost per speaking and per idle
session-second (tools/bench/live_clients.py `cpu_terms`, `cpu_split`), on a server whose CPU is known."""

from __future__ import annotations

import numpy as np
import pytest

from tools.bench.live_clients import CPU_SAMPLE_S, cpu_split, cpu_terms

BASE, SPEAKING, IDLE = 0.1, 0.02, 0.004  # cores, CPU s per speaking / idle session-second


def _clients(n: int = 50, stagger: float = 0.05) -> list[dict]:
    """Clients that answer staggered, speak 4 s and idle 1.5 s, as the bench's do; one failed client is skipped."""
    clients = [{"error": None, "answered": 1.0 + stagger * k, "interrupt_sent": 5.0 + stagger * k,
                "closed": 6.5 + stagger * k} for k in range(n)]
    return clients + [{"error": "RuntimeError: refused"}]


def _samples(clients: list[dict], noise: float, seed: int = 0) -> list[tuple[float, float]]:
    """The CPU seconds such a server has used, read every CPU_SAMPLE_S (with read noise, as /proc's ticks)."""
    live = [c for c in clients if not c["error"]]
    times = np.arange(0.0, 12.0, CPU_SAMPLE_S)
    fine = np.arange(0.0, 12.0, 0.001)
    rate = BASE + sum(SPEAKING * ((fine >= c["answered"]) & (fine < c["interrupt_sent"]))
                      + IDLE * ((fine >= c["interrupt_sent"]) & (fine < c["closed"])) for c in live)
    used = np.concatenate([[0.0], np.cumsum(rate) * 0.001])[np.searchsorted(fine, times)]
    return list(zip(times, used + np.random.default_rng(seed).normal(0, noise, len(times)), strict=True))


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_the_split_recovers_a_known_servers_costs(noise):
    clients = _clients()
    split = cpu_split([cpu_terms(clients, _samples(clients, noise))])
    assert split["intervals"] == 47
    tolerance = 0.002 if noise else 1e-3 * SPEAKING
    assert split["speaking_s_per_session_s"] == pytest.approx(SPEAKING, abs=tolerance)
    assert split["idle_s_per_session_s"] == pytest.approx(IDLE, abs=5 * tolerance)
    assert split["base_cores"] == pytest.approx(BASE, abs=0.02)


def test_rounds_pool_and_too_little_is_none():
    clients = _clients(20)
    one = cpu_terms(clients, _samples(clients, 0.0))
    both = cpu_split([one, cpu_terms(clients, _samples(clients, 0.0, seed=1))])
    assert both["intervals"] == 2 * one[0].shape[0]
    assert both["speaking_s_per_session_s"] == pytest.approx(SPEAKING, rel=1e-2)
    assert cpu_split([]) is None
    assert cpu_split([cpu_terms(clients, _samples(clients, 0.0)[:5])]) is None  # 4 intervals
    assert cpu_split([cpu_terms([], _samples(clients, 0.0))]) is None  # no session in them
