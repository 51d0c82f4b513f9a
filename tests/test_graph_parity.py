"""Each ONNX graph of the bundle against its torch module, on several inputs (tolerance: see
exporter/verify/bundle_verify.py). Quick run: the small speaker; full run: also the 20k-Gaussian demo speaker (conftest
`speaker_export`)."""

from __future__ import annotations

import numpy as np
import torch

from gaussiantalker.exporter.export.bundle_export import DEFORM_INPUTS
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.exporter.verify.bundle_verify import GRAPH_RTOL, verify_deformation, verify_translator
from gaussiantalker.runtime import TalkingHead


def test_translator_graph_matches_torch_at_other_lengths(speaker_export):
    # The graph was exported with 8 frames of audio; check 1, 25, 33 and 130 frames.
    with TalkingHead(speaker_export.path, resolution=(32, 32)) as head:
        result = verify_translator(speaker_export.speaker, head, frame_counts=(1, 25, 33, 130))
    assert result["passed"], result
    assert result["max_rel_err"] <= GRAPH_RTOL


def test_translator_graph_output_depends_on_audio(speaker_export):
    """Guard: the compared outputs are not constant (a translator returning zeros would also 'match')."""
    with TalkingHead(speaker_export.path, resolution=(32, 32)) as head:
        loud = synth_speech(1.0, seed=5)[:640 * 25]
        quiet = np.zeros_like(loud)
        jaw_loud = head.frame_renderer.graphs.run("translator", {"audio": loud[None]})["jaw_pose"]
        jaw_quiet = head.frame_renderer.graphs.run("translator", {"audio": quiet[None]})["jaw_pose"]
    assert np.abs(jaw_loud - jaw_quiet).max() > 0.05


def test_deformation_graph_matches_torch_on_random_drives(speaker_export):
    with TalkingHead(speaker_export.path, resolution=(32, 32)) as head:
        result = verify_deformation(speaker_export.speaker, head, count=8, seed=11)
    assert result["passed"], result
    assert result["cases"] == 8 * 4


def test_deformation_graph_batches(speaker_export):
    """The graph has a dynamic frame batch: 3 frames at once equal 3 single frames."""
    rng = np.random.default_rng(0)
    inputs = {"expression": rng.normal(0, 1, (3, 20)).astype(np.float32),
              "flame_pose": rng.normal(0, 0.1, (3, 15)).astype(np.float32),
              "head_translation": np.zeros((3, 3), np.float32),
              "camera_center": np.tile(np.float32([[0, 0, 0.9]]), (3, 1))}
    with TalkingHead(speaker_export.path, resolution=(32, 32)) as head:
        graphs = head.frame_renderer.graphs
        batched = graphs.run("deform", inputs)["means"]
        single = [graphs.run("deform", {k: v[i:i + 1] for k, v in inputs.items()})["means"][0] for i in range(3)]
    np.testing.assert_allclose(batched, np.stack(single), atol=1e-6)
    with torch.no_grad():
        reference = speaker_export.speaker.deform(*(torch.from_numpy(inputs[k]) for k in DEFORM_INPUTS))[0]
    np.testing.assert_allclose(batched, reference.numpy(), atol=1e-5)


def test_bundle_graphs_carry_no_debug_metadata(speaker_export):
    """The exporter's per-node stack traces are stripped: graphs hold only what runs (they were ~10x larger)."""
    import onnx

    from gaussiantalker.sdk.bundle import Bundle

    bundle = Bundle(speaker_export.path)
    for name in ("translator", "translator_stream", "translator_stream_steady", "deform"):
        model = onnx.ModelProto.FromString(bundle.graph_bytes(name))
        assert not any(node.metadata_props or node.doc_string for node in model.graph.node), name
        assert bundle.graph_info(name)["nbytes"] < 200_000, name
