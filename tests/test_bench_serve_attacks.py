"""`gt-bench serve-attacks` (tools/bench/serve_attacks.py) against gt-serve alone, on the small speaker's bundle:
every attack of docs/serve.md's threat model holds.

Bounds: the tool's own, each in its attack's docstring (a refusal within 3 s, 5 s, 15 s or 20 s; no more speaking
frames than espeak-ng's speech of the text itself plus 1 s); the attacks that wait on the server run at once, so
the run takes at most 20 s and a few more after the server has started."""

from __future__ import annotations

import shutil

import pytest
from ci_tools import need, need_module

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def test_every_attack_holds_on_gt_serve(small_export):
    for module in ("jwt", "prometheus_client", "aiohttp", "aiortc"):
        need_module(module, "serve")
    need(None if shutil.which("espeak-ng") else "espeak-ng is not installed (apt-get install espeak-ng)",
         ".ci/install")
    from tools.bench.serve_attacks import ATTACKS, run_serve_attacks

    result = run_serve_attacks(small_export.path, log=lambda line: None)
    (server,) = result["servers"]
    assert server["label"] == "gt-serve" and set(server["outcomes"]) == {attack.key for attack in ATTACKS}
    failed = {key: outcome for key, outcome in server["outcomes"].items() if outcome["held"] is not True}
    assert not failed, failed
    assert server["log_tracebacks"] == 0
