"""`gt-bench compare`: each version's worker imports that version, and a folder that is no checkout is refused.

Timings are not tested here (they belong in the benchmark); what is tested is that the two interpreters really
run two different copies of the SDK, which is what makes the side-by-side table mean anything.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tools.bench.compare import (
    PACKAGES,
    Version,
    _without_names,
    alternating,
    checkout_root,
    this_version_root,
)


def test_a_folder_without_the_packages_is_refused(tmp_path):
    (tmp_path / "sdk").mkdir()
    with pytest.raises(ValueError, match=r"is not a checkout of the SDK \(it has no src/gaussiantalker/ holding sdk/"):
        checkout_root(tmp_path)


def test_each_version_imports_its_own_copy(tmp_path):
    """A copy of this SDK is what the baseline interpreter imports, and this SDK what the other one imports."""
    copy = tmp_path / "copy"
    for name in PACKAGES:
        shutil.copytree(this_version_root() / name, copy / name, ignore=shutil.ignore_patterns("__pycache__"))
    versions = {label: Version.make(label, root, tmp_path) for label, root in (("this", this_version_root()),
                                                                                ("baseline", checkout_root(copy)))}
    probe = ("import gaussiantalker.sdk, gaussiantalker.runtime.head as h, pathlib; "
             "print(pathlib.Path(gaussiantalker.sdk.__file__).resolve().parent.parent, "
             "pathlib.Path(h.__file__).resolve().parent.parent)")
    for label, version in versions.items():
        out = subprocess.run([sys.executable, "-c", probe], env=version.env(), cwd=tmp_path, capture_output=True,
                             text=True, check=True).stdout.split()
        assert [Path(p) for p in out] == [version.root, version.root], (label, out)
    assert versions["baseline"].root != versions["this"].root


def test_rounds_alternate_which_version_goes_first():
    assert list(alternating(["a", "b"], 3)) == [(0, "a"), (0, "b"), (1, "b"), (1, "a"), (2, "a"), (2, "b")]


def test_the_baseline_checkpoint_drops_only_the_names(small_speaker, tmp_path):
    """Versions before named expressions reject their config keys; the copy the baseline exports lacks them and
    holds the same speaker (every tensor equal), and a binding other than the paper's is refused, not dropped."""
    import dataclasses

    import torch

    from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint

    original = save_checkpoint(small_speaker, tmp_path / "speaker.ckpt")
    copy = _without_names(original)
    config = torch.load(copy, weights_only=True)["config"]
    assert "expression_names" not in config and "binding" not in config
    before, after = load_checkpoint(original), load_checkpoint(copy)
    assert len(before.config.expression_names) == before.config.n_expr  # the demo speaker names its fields
    assert dataclasses.replace(before.config, expression_names=()) == after.config
    for module in ("gaussians", "latent_pose", "translator"):
        expected, actual = getattr(before, module).state_dict(), getattr(after, module).state_dict()
        assert expected.keys() == actual.keys()
        for name, tensor in expected.items():
            assert torch.equal(tensor, actual[name]), (module, name)
    payload = torch.load(original, weights_only=True)
    payload["config"]["binding"] = "scaled_triangle"
    torch.save(payload, tmp_path / "scaled.ckpt")
    with pytest.raises(ValueError, match="binding is 'triangle'"):
        _without_names(tmp_path / "scaled.ckpt")
