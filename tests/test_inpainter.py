"""Inpainting generator F: shapes, range, untrained behaviour (its priors), robustness, config, brief training, and
the ONNX graph against torch on several dynamic crop sizes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gaussiantalker.exporter.model.inpainter import (
    CROP_MULTIPLE,
    W_LOGIT_BIAS,
    InpainterConfig,
    InpainterNet,
    crop_multiple_ok,
    masked_l1,
    train_inpainter,
)

# fp32 on both sides and the same ops (convolutions, resizes, elementwise): only summation order differs, which
# moves results by a few ulp (~2e-7 measured); 1e-5 leaves room without hiding a wrong op.
ONNX_ATOL = 1e-5
PARITY_SIZES = ((48, 80), (256, 256), (320, 192))
HOLE_SHADE = 0.6  # the synthetic truth inside a hole is this much darker than the gradient around it


@pytest.fixture
def one_thread():
    """torch on one thread for the duration of a test: two threads on two busy cores can slow training 10x."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _gradient(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A smooth random colour gradient [3, H, W] in [0, 1]."""
    yy, xx = np.meshgrid(np.linspace(-1, 1, height), np.linspace(-1, 1, width), indexing="ij")
    base = rng.uniform(0.2, 0.8, (3, 1, 1))
    gx, gy = rng.uniform(-0.3, 0.3, (2, 3, 1, 1))
    return np.clip(base + gx * xx + gy * yy, 0.0, 1.0).astype(np.float32)


def _holed_scene(rng: np.random.Generator, batch: int = 8, size: int = 64, shade: float = 1.0):
    """(image, mask, coverage, target) tensors: gradients, a rectangular mask, a black uncovered rectangle inside
    it (coverage 0 there). The target is the gradient, times `shade` inside the hole."""
    target = np.stack([_gradient(rng, size, size) for _ in range(batch)])
    mask = np.zeros((batch, 1, size, size), np.float32)
    coverage = np.zeros_like(mask)
    for b in range(batch):
        top, left = rng.integers(4, 16, 2)
        height, width = rng.integers(36, 44, 2)
        mask[b, 0, top:top + height, left:left + width] = 1.0
        hole_top, hole_left = top + rng.integers(4, height // 2), left + rng.integers(4, width // 2)
        hole_h, hole_w = rng.integers(8, height // 2 - 2, 2)
        coverage[b, 0] = mask[b, 0]
        coverage[b, 0, hole_top:hole_top + hole_h, hole_left:hole_left + hole_w] = 0.0
    image = target * (1.0 - mask + coverage)  # x = I_gau + (1 - M) I_ori: black where the render left a hole
    target = target * (1.0 - (1.0 - shade) * mask * (1.0 - coverage))
    return tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in (image, mask, coverage, target))


def _random_inputs(seed: int, height: int, width: int) -> dict[str, np.ndarray]:
    """Inputs with a hole, a soft mask edge and colours slightly above 1."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.0, 1.05, (1, 3, height, width)).astype(np.float32)
    mask = np.clip(rng.uniform(-0.5, 1.5, (1, 1, height, width)), 0, 1).astype(np.float32)
    coverage = np.clip(rng.uniform(-0.5, 1.5, (1, 1, height, width)), 0, 1).astype(np.float32)
    coverage[..., height // 4:height // 2, width // 4:width // 2] = 0.0
    image[..., height // 4:height // 2, width // 4:width // 2] = 0.0
    return {"image": image, "mask": mask, "coverage": coverage}


def _torch_run(model: InpainterNet, inputs: dict[str, np.ndarray]) -> np.ndarray:
    with torch.no_grad():
        return model(*(torch.from_numpy(inputs[k]) for k in ("image", "mask", "coverage"))).numpy()


@pytest.fixture(scope="module")
def exported(inpaint_export):
    """The session's default-config F with random (non-zero) head weights, so the network's path shows in the
    output (conftest `inpaint_export`, a real torch.onnx export), and its ONNX session (one thread)."""
    import onnxruntime as ort

    model, proto = inpaint_export.model, inpaint_export.proto
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(proto.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return model, proto, session


def test_output_shape_dtype_and_range() -> None:
    torch.manual_seed(0)
    model = InpainterNet(InpainterConfig(channels=8, levels=2)).eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.head.weight, std=2.0)
        image = torch.rand(2, 3, 32, 48) * 1.2
        out = model(image, torch.rand(2, 1, 32, 48), torch.rand(2, 1, 32, 48))
    assert out.shape == (2, 3, 32, 48) and out.dtype == torch.float32
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0


def test_untrained_is_near_identity_on_a_fully_covered_crop() -> None:
    """Mask 1, coverage 1: no hole, and the head starts at zero, so w = sigmoid(W_LOGIT_BIAS) ≈ 0.0067 exactly
    everywhere and |F(x) - x| = w·|fill - x| ≤ w (both in [0, 1]; x above 1 is clamped). Measured ≈ 0.005."""
    torch.manual_seed(0)
    model = InpainterNet().eval()
    image = torch.rand(2, 3, 64, 96, generator=torch.Generator().manual_seed(1)) * 1.1
    ones = torch.ones(2, 1, 64, 96)
    with torch.no_grad():
        out = model(image, ones, ones)
    bound = 1.0 / (1.0 + math.exp(-W_LOGIT_BIAS))
    assert float((out - image.clamp(0, 1)).abs().max()) <= bound + 1e-6


def test_untrained_fills_a_hole_from_its_surroundings() -> None:
    """The push-pull fill prior and the hole term of w: holes up to 20x20 in smooth gradients come back within
    0.05 (measured over seeds 0-5: mean ≤ 0.008, max ≤ 0.032; black, they were ~0.45 off). Covered pixels move by
    w·|fill - x| with w = sigmoid(W_LOGIT_BIAS) ≈ 0.0067 and a fill close to x (measured ≤ 0.0012)."""
    torch.manual_seed(0)
    model = InpainterNet().eval()
    image, mask, coverage, target = _holed_scene(np.random.default_rng(3), batch=4)
    with torch.no_grad():
        out = model(image, mask, coverage)
    hole = (mask * (1 - coverage)).bool().expand_as(out)
    error = (out - target).abs()
    assert float((image - target).abs()[hole].mean()) > 0.2  # the hole really is there
    assert float(error[hole].max()) < 0.05 and float(error[hole].mean()) < 0.02
    assert float(error[~hole].max()) < 0.005


@pytest.mark.parametrize("value", [0.0, 1.0, 1e4, -1e4, float("nan"), float("inf"), -float("inf")])
def test_finite_output_for_extreme_inputs(value: float) -> None:
    torch.manual_seed(0)
    model = InpainterNet().eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.head.weight, std=1.0)
        full = torch.full((1, 3, 32, 32), value)
        plane = torch.full((1, 1, 32, 32), value)
        for inputs in ((full, plane, plane), (full, torch.ones(1, 1, 32, 32), torch.zeros(1, 1, 32, 32))):
            out = model(*inputs)
            assert torch.isfinite(out).all(), inputs
            assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0


def test_crop_sides_must_be_multiples_of_crop_multiple() -> None:
    model = InpainterNet().eval()
    assert CROP_MULTIPLE == 16
    assert crop_multiple_ok(16, 320) and not crop_multiple_ok(40, 64) and not crop_multiple_ok(0, 16)
    with pytest.raises(ValueError, match="40x64 is not a multiple of 16"):
        model(torch.zeros(1, 3, 40, 64), torch.zeros(1, 1, 40, 64), torch.zeros(1, 1, 40, 64))


def test_config_round_trip_and_errors() -> None:
    config = InpainterConfig(channels=8, levels=2)
    assert InpainterConfig.from_dict(config.to_dict()) == config
    assert InpainterConfig.from_dict({}) == InpainterConfig()
    assert InpainterConfig.from_dict({"channels": np.int64(24)}).channels == 24
    for data, field in (({"channel": 8}, "channel"), ({"channels": 0}, "channels"), ({"levels": -1}, "levels"),
                        ({"levels": 4}, "levels"), ({"channels": 1.5}, "channels"), ({"levels": True}, "levels"),
                        ({"channels": "16"}, "channels")):
        with pytest.raises(ValueError, match=field):
            InpainterConfig.from_dict(data)


def test_brief_training_lowers_the_masked_loss(one_thread) -> None:
    """100 Adam steps on 8 crops of 64x64 (~1.5 s). The untrained F already fills smooth gradients almost exactly,
    so the truth inside each hole is HOLE_SHADE darker (a shadowed chin): only training can learn that. Measured
    over seeds 0-7: final/initial loss 0.16-0.25 (seed 0: 0.22); the step count, not the clock, stops it."""
    torch.manual_seed(0)
    model = InpainterNet()
    losses = train_inpainter(model, lambda rng: _holed_scene(rng, shade=HOLE_SHADE), seconds=300.0, max_steps=100,
                           seed=0)
    assert len(losses) == 100 and all(math.isfinite(v) for v in losses)
    assert not model.training
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:10]), (losses[:10], losses[-10:])
    with torch.no_grad():  # and on a held-out batch
        image, mask, coverage, target = _holed_scene(np.random.default_rng(99), shade=HOLE_SHADE)
        untrained = InpainterNet().eval()
        before = float(masked_l1(untrained(image, mask, coverage), target, mask))
        after = float(masked_l1(model(image, mask, coverage), target, mask))
    assert after < 0.5 * before


def test_training_stops_on_the_clock() -> None:
    model = InpainterNet(InpainterConfig(channels=4, levels=1))
    assert train_inpainter(model, lambda rng: _holed_scene(rng, batch=1, size=32), seconds=0.0) == []
    assert not model.training


def test_onnx_graph_matches_torch_on_dynamic_sizes(exported) -> None:
    model, _, session = exported
    for seed, (height, width) in enumerate(PARITY_SIZES):
        inputs = _random_inputs(seed, height, width)
        (onnx_out,) = session.run(["inpainted"], inputs)
        torch_out = _torch_run(model, inputs)
        assert onnx_out.shape == (1, 3, height, width)
        np.testing.assert_allclose(onnx_out, torch_out, rtol=0, atol=ONNX_ATOL, err_msg=f"{height}x{width}")


def test_onnx_output_depends_on_the_network(exported) -> None:
    """Guard: the compared outputs are not just the parameter-free priors (an all-zero head would also match)."""
    model, _, session = exported
    inputs = _random_inputs(5, 64, 64)
    prior_only = InpainterNet().eval()
    assert np.abs(session.run(None, inputs)[0] - _torch_run(prior_only, inputs)).max() > 0.05


def test_onnx_graph_interface(exported) -> None:
    _, proto, _ = exported
    shapes = {v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
              for v in (*proto.graph.input, *proto.graph.output)}
    assert list(shapes) == ["image", "mask", "coverage", "inpainted"]
    assert shapes["image"][:2] == [1, 3] and shapes["mask"][:2] == [1, 1] and shapes["inpainted"][:2] == [1, 3]
    assert all(isinstance(d, str) for shape in shapes.values() for d in shape[2:])  # H and W are dynamic


def test_onnx_graph_is_finite_for_non_finite_inputs(exported) -> None:
    _, _, session = exported
    image = np.full((1, 3, 32, 48), np.nan, np.float32)
    image[..., :8, :] = np.inf
    image[..., 8:16, :] = 1e4
    mask = np.full((1, 1, 32, 48), np.nan, np.float32)
    coverage = np.full((1, 1, 32, 48), -np.inf, np.float32)
    (out,) = session.run(None, {"image": image, "mask": mask, "coverage": coverage})
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0


def test_onnx_graph_fails_loudly_on_a_size_not_a_multiple(exported) -> None:
    """The graph has no size check of its own: off-multiple sizes break a skip connection's shapes."""
    _, _, session = exported
    inputs = {k: np.ascontiguousarray(v[..., :40, :40]) for k, v in _random_inputs(0, 48, 48).items()}
    with pytest.raises(Exception, match="ONNXRuntimeError"):
        session.run(None, inputs)
