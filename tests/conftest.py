"""Shared fixtures: the default demo speaker (built once per session, deterministic) and its fp32 bundle."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def demo_speaker():
    """The default demo speaker (20k Gaussians, translator trained as `make_demo_speaker.py` does)."""
    from gaussiantalker.exporter.demo_speaker import make_demo_speaker

    speaker, metrics = make_demo_speaker(progress=False)
    speaker.metrics = metrics
    return speaker


@pytest.fixture(scope="session")
def demo_bundle(demo_speaker, tmp_path_factory):
    """The demo speaker exported as an fp32 bundle."""
    from gaussiantalker.exporter.export import export_bundle

    path = tmp_path_factory.mktemp("bundle") / "demo.gtb"
    export_bundle(demo_speaker, path, progress=False)
    return path


@pytest.fixture(scope="session")
def small_speaker():
    """A 2k-Gaussian untrained speaker for tests that exercise plumbing, not quality."""
    from gaussiantalker.exporter.demo_speaker import make_demo_speaker

    speaker, _ = make_demo_speaker(n_gaussians=2000, seed=3, train_seconds=0, progress=False)
    return speaker
