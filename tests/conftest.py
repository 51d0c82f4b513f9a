"""Shared fixtures, each built once per session (deterministic): the demo speaker and its fp32 bundle, a small
untrained speaker and its bundle (with the ONNX protos torch.onnx made for it, so tests can re-export in ~1 s)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest


@pytest.fixture(scope="session")
def demo_speaker():
    """The default demo speaker (20k Gaussians, translator trained as `make_demo_speaker.py` does)."""
    from gaussiantalker.exporter.demo_speaker import make_demo_speaker

    speaker, metrics = make_demo_speaker(progress=False)
    speaker.metrics = metrics
    return speaker


def _export_recording(speaker, path) -> SimpleNamespace:
    """Export `speaker` to `path`, keeping the two ONNX protos torch.onnx made (translator, deform)."""
    import gaussiantalker.exporter.onnx_export as onnx_export_module
    from gaussiantalker.exporter.export import export_bundle

    protos = []
    real_export_onnx = onnx_export_module.export_onnx

    def recording(*args, **kwargs):
        protos.append(real_export_onnx(*args, **kwargs))
        return protos[-1]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(onnx_export_module, "export_onnx", recording)
        export_bundle(speaker, path, progress=False)
    return SimpleNamespace(path=path, protos=protos)


@pytest.fixture(scope="session")
def demo_export(demo_speaker, tmp_path_factory) -> SimpleNamespace:
    """The demo speaker exported as an fp32 bundle (`.path`) and its ONNX protos (`.protos`)."""
    return _export_recording(demo_speaker, tmp_path_factory.mktemp("bundle") / "demo.gtb")


@pytest.fixture(scope="session")
def demo_bundle(demo_export):
    """The demo speaker exported as an fp32 bundle."""
    return demo_export.path


@pytest.fixture(scope="session")
def small_speaker():
    """A 2k-Gaussian untrained speaker for tests that exercise plumbing, not quality."""
    from gaussiantalker.exporter.demo_speaker import make_demo_speaker

    speaker, _ = make_demo_speaker(n_gaussians=2000, seed=3, train_seconds=0, progress=False)
    return speaker


@pytest.fixture(scope="session")
def small_export(small_speaker, tmp_path_factory) -> SimpleNamespace:
    """`small_speaker` exported once: `.path` the fp32 bundle, `.protos` its two ONNX graphs as torch.onnx made
    them (translator, deform) for tests that export again without paying for torch.onnx."""
    return _export_recording(small_speaker, tmp_path_factory.mktemp("small") / "small.gtb")


@pytest.fixture
def replay_onnx_exports(monkeypatch):
    """`replay_onnx_exports(protos)`: the next exports reuse `protos` (in export order) instead of running
    torch.onnx again; the rest of the export (codecs, bundle writing) runs for real."""
    import gaussiantalker.exporter.onnx_export as onnx_export_module

    def replay(protos) -> None:
        queue = iter(protos)
        monkeypatch.setattr(onnx_export_module, "export_onnx", lambda *args, **kwargs: next(queue))

    return replay


# -- stability table --------------------------------------------------------------------------------------------
# Stability tests call `stability.record(area, case, behaviour)` with what they observed (not what they expect):
# `GT_STABILITY_TABLE=out/stability.md python -m pytest tests/test_stability_*.py` writes the README's table.

_STABILITY_ROWS: list[tuple[str, str, str, str]] = []


class StabilityRecorder:
    """Collects (area, case, observed behaviour) rows for the stability table of one test."""

    def __init__(self, test_id: str) -> None:
        self.test_id = test_id

    def record(self, area: str, case: str, behaviour: str) -> None:
        _STABILITY_ROWS.append((area, case, behaviour, self.test_id))


@pytest.fixture
def stability(request) -> StabilityRecorder:
    return StabilityRecorder(request.node.nodeid)


def pytest_sessionfinish(session, exitstatus):
    import os
    from pathlib import Path

    target = os.environ.get("GT_STABILITY_TABLE")
    if not target or not _STABILITY_ROWS:
        return
    rows = sorted(set(_STABILITY_ROWS))
    lines = [f"{len(rows)} cases, recorded by the tests ({'all passed' if exitstatus == 0 else 'NOT all passed'}).",
             "", "| area | case | behaviour | test |", "|---|---|---|---|"]
    for area, case, behaviour, test_id in rows:
        cells = (c.replace("|", "\\|") for c in (area, case, behaviour, test_id.split("::")[0].split("/")[-1]))
        lines.append("| " + " | ".join(cells) + " |")
    Path(target).parent.mkdir(parents=True, exist_ok=True)
    Path(target).write_text("\n".join(lines) + "\n")
