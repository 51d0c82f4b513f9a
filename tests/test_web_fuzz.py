"""The browser player's bundle reader (web/src/bundle.js, run by node) on the same seeded mutations as the Python
reader's fuzz (tests/test_fuzz_readers.py): header fields set to 0/-1/huge, bytes mutated anywhere, manifest values
swapped under a matching digest. Every case either loads (every buffer decoded, every graph's bytes read) or is
refused with one BundleError line naming the file, never another exception or a hang, and the JS reader's verdict
is the Python reader's, case by case (docs/web.md, "Reading a bundle").

Needs node (.ci/browser's npm brings it in CI, where this test fails without it)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need
from fuzz_mutations import dumps, mutate_bytes, mutate_field_bytes, mutate_json
from test_fuzz_readers import _bundle_with_manifest, small_bundle  # noqa: F401  (a fixture)

from gaussiantalker.sdk.bundle import HEADER_SIZE, MAX_MANIFEST_DEPTH, Bundle
from gaussiantalker.sdk.errors import BundleError

ROOT = Path(__file__).resolve().parents[1]
CASES = {"ci": 300, "heavy": 3000}
# Seconds the node process may take for all cases (each is a few kB; the CI run takes about a second).
NODE_TIMEOUT_S = 300

SCRIPT = """
import fs from 'node:fs';
import { readBundle, BundleError } from %(bundle_js)s;
const results = [];
for (const path of JSON.parse(fs.readFileSync(%(list)s, 'utf8'))) {
  try {
    const bundle = await readBundle(fs.readFileSync(path), { name: path });
    for (const name of Object.keys(bundle.manifest.buffers)) bundle.buffer(name);
    for (const name of bundle.graphNames()) await bundle.graphBytes(name);
    results.push({ verdict: 'loaded' });
  } catch (error) {
    results.push({ verdict: error instanceof BundleError ? 'refused' : 'crashed',
                   message: `${error?.constructor?.name}: ${error?.message}` });
  }
}
console.log(JSON.stringify(results));
"""


def _python_verdict(path: Path) -> str:
    """What the Python reader says of a file, read as tests/test_fuzz_readers.py reads it."""
    try:
        bundle = Bundle(path)
        bundle.verify_all()
        for name in bundle.manifest["buffers"]:
            bundle.buffer(name)
        for name in bundle.manifest["graphs"]:
            bundle.graph_bytes(name)
    except BundleError:
        return "refused"
    return "loaded"


def _cases(data: bytes, folder: Path, count: int, seed: int) -> list[tuple[Path, str]]:
    """(file, what was done) for `count` seeded mutations of the bundle `data`, as the Python fuzz makes them."""
    length = struct.unpack_from("<Q", data, 16)[0]
    manifest = json.loads(data[HEADER_SIZE:HEADER_SIZE + length])
    header_fields = [(8, 2), (10, 2), (12, 4), (16, 8), (56, 8)]
    rng = np.random.default_rng(seed)
    cases = []
    for index in range(count):
        choice = rng.random()
        if choice < 0.55:
            changed, what = mutate_json(manifest, rng)
            mutated = _bundle_with_manifest(data, dumps(changed))
        elif choice < 0.7:
            mutated, what = mutate_field_bytes(data, rng, header_fields)
        else:
            mutated, what = mutate_bytes(data, rng)
        path = folder / f"case{index:05d}.gtb"
        path.write_bytes(mutated)
        cases.append((path, what))
    for depth in (MAX_MANIFEST_DEPTH, MAX_MANIFEST_DEPTH + 1):  # either side of the nesting bound
        path = folder / f"depth{depth}.gtb"
        path.write_bytes(_bundle_with_manifest(data, dumps({**manifest, "note": _nested(depth - 1)})))
        cases.append((path, f"a manifest {depth} deep"))
    return cases


def _nested(levels: int) -> object:
    """A value that is `levels` arrays deep."""
    value: object = 0
    for _ in range(levels):
        value = [value]
    return value


@pytest.mark.parametrize("run, seed", [pytest.param("ci", 0, id="ci"),
                                       pytest.param("heavy", 1000, id="heavy", marks=pytest.mark.heavy)])
def test_fuzz_the_web_bundle_reader(small_bundle, tmp_path, run, seed):  # noqa: F811  (the imported fixture)
    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    cases = _cases(small_bundle, tmp_path, CASES[run], seed + 9)
    listing = tmp_path / "cases.json"
    listing.write_text(json.dumps([str(path) for path, _ in cases]))
    script = tmp_path / "fuzz.mjs"
    script.write_text(SCRIPT % {"bundle_js": json.dumps((ROOT / "web" / "src" / "bundle.js").as_uri()),
                                "list": json.dumps(str(listing))})
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    results = json.loads(done.stdout)
    assert len(results) == len(cases)
    problems, verdicts = [], {"loaded": 0, "refused": 0}
    for (path, what), result in zip(cases, results, strict=True):
        where = f"{path.name} ({what})"
        if result["verdict"] == "crashed":
            problems.append(f"{where}: not a BundleError: {result['message'][:300]}")
            continue
        verdicts[result["verdict"]] += 1
        if result["verdict"] == "refused" and ("\n" in result["message"] or str(path) not in result["message"]):
            problems.append(f"{where}: the message is not one line naming the file: {result['message'][:300]!r}")
        python = _python_verdict(path)
        if python != result["verdict"]:
            problems.append(f"{where}: Python {python}, web {result['verdict']} ({result.get('message', '')[:200]})")
    assert not problems, "\n".join(problems[:20]) + f"\n({len(problems)} in all)"
    assert verdicts["refused"] > len(cases) // 2 and verdicts["loaded"] > 0, verdicts  # the cases reach both ends


def test_both_readers_bound_the_manifest_alike():
    """The sizes and depths the JS reader refuses are the Python reader's (sdk/bundle.py)."""
    import re

    from gaussiantalker.sdk import bundle

    source = (ROOT / "web" / "src" / "bundle.js").read_text()
    for name in ("MAX_MANIFEST_BYTES", "MAX_MANIFEST_DEPTH"):
        (expression,) = re.findall(rf"export const {name} = ([0-9 *]+);", source)
        assert eval(expression, {"__builtins__": {}}) == getattr(bundle, name), name  # digits and * only


def test_a_manifest_nesting_past_the_bound_is_refused(small_bundle, tmp_path):  # noqa: F811
    """One level past MAX_MANIFEST_DEPTH is refused by the Python reader (the JS one: the fuzz's last two cases);
    the bound itself loads."""
    length = struct.unpack_from("<Q", small_bundle, 16)[0]
    manifest = json.loads(small_bundle[HEADER_SIZE:HEADER_SIZE + length])
    for depth, verdict in ((MAX_MANIFEST_DEPTH, "loaded"), (MAX_MANIFEST_DEPTH + 1, "refused")):
        path = tmp_path / f"depth{depth}.gtb"  # the manifest itself is level 1
        path.write_bytes(_bundle_with_manifest(small_bundle, dumps({**manifest, "note": _nested(depth - 1)})))
        assert _python_verdict(path) == verdict, depth
    with pytest.raises(BundleError, match="manifest is not valid JSON: it nests too deep"):
        Bundle(path)
