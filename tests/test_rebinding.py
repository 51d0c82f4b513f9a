"""The tests' `export_rebound` (conftest): a recorded torch.onnx export with another speaker's weights bound in by
name is that speaker's real export, and anything that would make it not so is refused."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
from gaussiantalker.exporter.export.bundle_export import DEFORM_INPUTS
from gaussiantalker.exporter.export.deform_graph import DeformationGraph
from gaussiantalker.exporter.model.translator_stream import MotionTranslatorStream
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.drive import FrameDrive, HeadPose


def _other_speaker():
    """The small speaker's architecture with every weight different: another seed (head, Gaussians, MLPs) and a
    perturbed translator (an untrained one has a zero head, which would hide a wrong binding)."""
    speaker, _ = make_demo_speaker(n_gaussians=2000, seed=4, train_seconds=0, progress=False)
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for parameter in speaker.translator.parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))
    return speaker.eval()


@pytest.mark.slow  # one real torch.onnx export of a 2k speaker (~10 s)
def test_rebound_export_equals_a_real_export(small_export, export_rebound, export_recording, tmp_path):
    other = _other_speaker()
    rebound = export_rebound(other, tmp_path / "rebound.gtb", small_export)
    real = export_recording(other, tmp_path / "real.gtb")
    first, second = Bundle(rebound.path), Bundle(real.path)
    assert first.manifest["buffers"].keys() == second.manifest["buffers"].keys()
    differs = 0
    for name in first.manifest["buffers"]:
        np.testing.assert_array_equal(first.buffer(name), second.buffer(name), err_msg=name)
        differs += name.startswith("deform/") and not np.array_equal(first.buffer(name),
                                                                     Bundle(small_export.path).buffer(name))
    assert differs >= 10  # the speakers really differ: the check above could fail
    for graph in ("translator", "translator_stream", "translator_stream_steady", "deform"):
        assert first.graph_bytes(graph) == second.graph_bytes(graph), graph
    assert rebound.path.read_bytes() == real.path.read_bytes()

    rng = np.random.default_rng(0)
    with TalkingHead(rebound.path, resolution=(32, 32)) as a, TalkingHead(real.path, resolution=(32, 32)) as b:
        for drive in (FrameDrive.make(20), FrameDrive.make(20, rng.normal(0, 1, 20), [0.3, 0, 0],
                                                            head_pose=HeadPose.make([0.1, 0.2, 0.0]))):
            inputs = drive.graph_inputs() | {"camera_center": a.camera.center.astype(np.float32)[None]}
            out_a, out_b = a.frame_renderer.graphs.run("deform", inputs), b.frame_renderer.graphs.run("deform", inputs)
            for name in out_a:
                np.testing.assert_array_equal(out_a[name], out_b[name])
            with torch.no_grad():
                means = other.deform(*(torch.from_numpy(inputs[k]) for k in DEFORM_INPUTS))[0].numpy()
            np.testing.assert_allclose(out_a["means"], means, atol=1e-5)
        audio = 0.1 * rng.standard_normal((1, 640 * 9)).astype(np.float32)
        np.testing.assert_array_equal(a.frame_renderer.graphs.run("translator", {"audio": audio})["jaw_pose"],
                                      b.frame_renderer.graphs.run("translator", {"audio": audio})["jaw_pose"])


@pytest.mark.parametrize("recorded", [pytest.param("demo_export", marks=pytest.mark.slow), "small_export"])
def test_rebinding_the_recorded_speaker_gives_the_recorded_graphs(recorded, rebind_onnx, request):
    """Every initializer torch.onnx made is found by name, with the very bytes it had."""
    export = request.getfixturevalue(recorded)
    translator = export.speaker.translator
    modules = (translator, MotionTranslatorStream(translator), MotionTranslatorStream(translator, call_refresh=0),
               DeformationGraph(export.speaker))  # export order
    for proto, module in zip(export.protos, modules, strict=True):
        assert rebind_onnx(proto, module, module).SerializeToString() == proto.SerializeToString()


def test_rebinding_refuses_another_architecture(small_speaker, small_export, rebind_onnx):
    translator, _, _, deform = small_export.protos
    # 2100 Gaussians instead of 2000: same names, other shapes (the deformation graph records its size).
    larger, _ = make_demo_speaker(n_gaussians=2100, seed=3, train_seconds=0, progress=False)
    with pytest.raises(AssertionError, match=r"settings differ from the recorded module's: .n_gaussians 2000 -> 2100"):
        rebind_onnx(deform, DeformationGraph(larger), DeformationGraph(small_speaker))
    # Another speaker id: the same tensors, but torch.onnx baked the id into the graph.
    other_id = copy.deepcopy(small_speaker.translator)
    other_id.speaker_id = 1
    with pytest.raises(AssertionError, match="speaker_id 0 -> 1"):
        rebind_onnx(translator, other_id, small_speaker.translator)
    # A weight the module does not have under the recorded name.
    renamed = copy.deepcopy(small_speaker.translator)
    renamed.motion_decoder.output_head = renamed.motion_decoder.head
    del renamed.motion_decoder.head
    with pytest.raises(AssertionError, match=r"'motion_decoder\.head\.weight' .* has no parameter or buffer"):
        rebind_onnx(translator, renamed, renamed)
