"""Every buffer at the fp16 codec, measured against the fp32 torch speaker (bounds: Tolerances.for_codec)."""

from __future__ import annotations

import os
import stat

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.verify.bundle_verify import Tolerances, verify_bundle
from gaussiantalker.sdk.bundle import Bundle


def test_fp16_buffers_halve_the_bundle_within_their_tolerance(speaker_export, tmp_path, replay_onnx_exports):
    replay_onnx_exports(speaker_export.protos)  # same graphs; only the buffer codec differs
    path = tmp_path / "fp16.gtb"
    export_bundle(speaker_export.speaker, path, codec="fp16", progress=False)
    assert os.path.getsize(path) < 0.6 * os.path.getsize(speaker_export.path)
    assert Bundle(path).manifest["precision"] == "fp16"
    report = verify_bundle(speaker_export.speaker, path, frames=5, resolution=(128, 128),
                           tolerances=Tolerances.for_codec("fp16"), progress=False)
    assert report["passed"], report
    # ...and it is really a different export: the fp32 bounds would not hold for it.
    assert report["graphs"]["deform"]["max_rel_err"] > Tolerances().graph_rtol / 10


def test_bundle_is_an_ordinary_readable_file(speaker_export):
    mode = stat.S_IMODE(os.stat(speaker_export.path).st_mode)
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask
