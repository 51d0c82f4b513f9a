"""The FLAME pickle reader fuzzed (tests/flame_fuzz.py): value-level and opcode-level mutations of FLAME-layout
pickles, run in a child process so that a crash is a failure naming its case, not the end of the test run.

Every case must load into arrays that own exactly their file's bytes (plain dtypes, no views, no more bytes than the
file), or be refused with one ImportFormatError line that starts with the file's path; any other exception, a
signal or a line break in the message fails. The quick run has 400 cases (a few seconds); the heavy run 4 seeds of
5,000 (`GT_HEAVY=1 python -m pytest -q -m heavy tests/test_flame_pkl_fuzz.py`, docs/untrusted-input.md).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from flame_fuzz import array_problems, check_case, make_case, refusal_outcome

from gaussiantalker.sdk.errors import ImportFormatError

FUZZER = Path(__file__).with_name("flame_fuzz.py")


def _fuzz(seed: int, cases: int, timeout: float) -> dict:
    """Run the fuzzer in a child process; fail with the case a crash hit."""
    done = subprocess.run([sys.executable, str(FUZZER), "--seed", str(seed), "--cases", str(cases)],
                          capture_output=True, text=True, timeout=timeout)
    if done.returncode < 0:
        last = done.stderr.strip().splitlines()[-1:] or ["before the first case"]
        pytest.fail(f"the fuzzer died by {signal.Signals(-done.returncode).name} at {last[0]} (seed {seed})")
    lines = done.stdout.strip().splitlines()
    assert lines, done.stderr[-2000:]
    summary = json.loads(lines[-1])
    assert summary["failures"] == [], "\n".join(lines[:-1])[:4000]
    assert done.returncode == 0, done.stderr[-2000:]
    return summary


def test_fuzz_quick():
    summary = _fuzz(seed=1, cases=400, timeout=300)
    assert summary["loaded"] + summary["refused"] == 400
    # the mutations reach both outcomes: some cases stay valid FLAME pickles and load through convert_flame_pkl
    assert summary["loaded"] >= 10 and summary["refused"] >= 200


@pytest.mark.heavy
@pytest.mark.parametrize("seed", [2, 3, 4, 5])
def test_fuzz_heavy(seed):
    summary = _fuzz(seed=seed, cases=5000, timeout=1800)
    assert summary["loaded"] + summary["refused"] == 5000


def test_cases_are_deterministic():
    """A case is a function of (seed, index) alone, so a failing case can be rebuilt from its number."""
    assert [make_case(i, 3) for i in range(20)] == [make_case(i, 3) for i in range(20)]
    assert len({make_case(i, 3) for i in range(20)}) == 20


def test_checker_catches_what_it_looks_for(tmp_path):
    """The fuzzer's checks fail on the arrays a trusting reader would return: a view of other memory, a structured
    dtype, more bytes than the file; and on a refusal that is not one line naming the file."""
    owner = np.zeros(100)
    assert array_problems({"a": owner[:4]}, 10_000) == ["an array of shape (4,) is a view of other memory"]
    assert "is not plain" in array_problems({"a": [np.zeros(2, dtype="f8,i4")]}, 10_000)[0]
    assert array_problems({"a": np.zeros(100)}, 799) == ["an array of 800 bytes from a 799-byte file"]
    assert array_problems({"a": np.zeros(100)}, 800) == []
    (tmp_path / "list.pkl").write_bytes(b"\x80\x02]q\x00.")
    outcome, detail = check_case(tmp_path / "list.pkl", tmp_path / "out.npz")
    assert outcome == "refused" and detail.startswith(f"{tmp_path / 'list.pkl'}: the pickle holds a list")
    path = tmp_path / "list.pkl"
    assert refusal_outcome(path, ImportFormatError("list.pkl: elsewhere"))[0] == "FAILED"
    assert refusal_outcome(path, ImportFormatError(f"{path}: two\nlines"))[0] == "FAILED"
