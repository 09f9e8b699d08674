"""Direction-aware convolution (DA-Occ's DAC): shapes, directionality, circular semantics, gradients, ONNX."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch.func import functional_call

from occkit.models.complexity import count_parameters
from occkit.models.dac import DACBlock, DirectionAwareConv, band_index, direction_aware_conv

DIRECTIONS = ("v", "h")
PADDINGS = ("circular", "zeros")
SHAPE = (2, 3, 5, 7)  # (B, C, H, W), non-square


def _axis(direction: str) -> int:
    return 2 if direction == "v" else 3


def _length(direction: str, shape: tuple[int, ...] = SHAPE) -> int:
    return shape[_axis(direction)]


def _dac(direction: str, padding: str = "circular", shape: tuple[int, ...] = SHAPE, seed: int = 0, **kwargs):
    torch.manual_seed(seed)
    return DirectionAwareConv(shape[1], _length(direction, shape), direction, padding, **kwargs)


def _freeze_dynamic_part(dac: DirectionAwareConv) -> None:
    """Zero the generator's last layer, so the kernel is the static base kernel whatever the input."""
    with torch.no_grad():
        dac.mlp[2].weight.zero_()
        dac.mlp[2].bias.zero_()


def _roll_reference(x: torch.Tensor, kernel: torch.Tensor, direction: str, padding: str) -> torch.Tensor:
    """``out[i] = sum_k K[k] x[(i + k) mod L]`` (circular) or without the wrapped terms (zeros), by shifted copies."""
    axis = _axis(direction)
    length = x.shape[axis]
    out = torch.zeros_like(x)
    for k in range(length):
        if padding == "circular":
            shifted = torch.roll(x, -k, axis)  # shifted[i] = x[(i + k) mod L]
        else:
            shifted = torch.zeros_like(x)
            shifted.narrow(axis, 0, length - k).copy_(x.narrow(axis, k, length - k))
        out = out + kernel[..., k][..., None, None] * shifted
    return out


def _concat_reference(x: torch.Tensor, kernel: torch.Tensor, direction: str, padding: str) -> torch.Tensor:
    """The paper's formulation: concatenate the shifted copy (or zeros), then a "valid" grouped conv2d."""
    batch, channels, height, width = x.shape
    axis = _axis(direction)
    length = x.shape[axis]
    head = x.narrow(axis, 0, length - 1)
    tail = head if padding == "circular" else torch.zeros_like(head)
    stacked = torch.cat([x, tail], axis)  # length 2L - 1 along the axis
    stacked = stacked.reshape(1, batch * channels, *stacked.shape[2:])
    size = (length, 1) if direction == "v" else (1, length)
    out = F.conv2d(stacked, kernel.reshape(batch * channels, 1, *size), groups=batch * channels)
    return out.reshape(batch, channels, height, width)


@pytest.mark.parametrize("padding", PADDINGS)
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_output_shapes(direction, padding):
    for shape in (SHAPE, (1, 4, 9, 2), (3, 2, 1, 6)):
        dac = _dac(direction, padding, shape)
        block = DACBlock(shape[1], _length(direction, shape), direction, padding)
        x = torch.randn(shape)
        assert dac(x).shape == shape
        assert block(x).shape == shape
        assert dac.dynamic_kernel(x).shape == (shape[0], shape[1], _length(direction, shape))


def test_block_is_dac_without_bias_then_batchnorm_relu():
    block = DACBlock(4, 6, "v")
    assert block.conv.bias is None and block.conv.direction == "v"
    assert isinstance(block.bn, torch.nn.BatchNorm2d) and isinstance(block.act, torch.nn.ReLU)
    assert (block(torch.randn(2, 4, 6, 3)) >= 0).all()


@pytest.mark.parametrize("padding", PADDINGS)
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_impulse_with_fixed_kernel_stays_on_its_line(direction, padding):
    dac = _dac(direction, padding)
    _freeze_dynamic_part(dac)
    x = torch.randn(SHAPE)
    h0, w0 = 3, 4
    bumped = x.clone()
    bumped[:, :, h0, w0] += 1.0
    with torch.no_grad():
        change = (dac(bumped) - dac(x)).abs().amax(dim=(0, 1))  # (H, W)
    if direction == "v":
        outside, line = torch.cat([change[:, :w0], change[:, w0 + 1 :]], 1), change[:, w0]
        reached = torch.arange(SHAPE[2]) <= h0 if padding == "zeros" else torch.ones(SHAPE[2], dtype=torch.bool)
    else:
        outside, line = torch.cat([change[:h0], change[h0 + 1 :]], 0), change[h0]
        reached = torch.arange(SHAPE[3]) <= w0 if padding == "zeros" else torch.ones(SHAPE[3], dtype=torch.bool)
    assert outside.max() == 0
    # Circular: the whole line changes; zeros: out[i] sees x[i..L-1], so only positions up to the impulse.
    assert (line[reached] > 1e-6).all() and (line[~reached] == 0).all()


@pytest.mark.parametrize("direction", DIRECTIONS)
def test_pooling_is_directional(direction):
    dac = _dac(direction)
    with torch.no_grad():
        torch.nn.init.normal_(dac.mlp[2].weight, std=0.5)  # a strongly input-dependent kernel
    x = torch.randn(SHAPE)
    other = 3 if direction == "v" else 2  # the axis the pooling averages out
    pooled = dac.pool(x)
    assert pooled.shape == (SHAPE[0], SHAPE[1], _length(direction))
    torch.testing.assert_close(pooled, x.mean(other))
    perm_other = torch.randperm(SHAPE[other], generator=torch.Generator().manual_seed(1))
    perm_own = torch.arange(_length(direction)).roll(1)
    with torch.no_grad():
        # Permuting along the averaged axis leaves the kernel alone and, as the encoding is constant along it,
        # permutes the output the same way: the dynamic DAC still mixes only along its own axis.
        torch.testing.assert_close(dac.dynamic_kernel(x.index_select(other, perm_other)), dac.dynamic_kernel(x))
        torch.testing.assert_close(dac(x.index_select(other, perm_other)), dac(x).index_select(other, perm_other))
        # Reordering along its own axis changes the pooled profile, hence the kernel.
        moved = x.index_select(_axis(direction), perm_own)
        assert not torch.allclose(dac.dynamic_kernel(moved), dac.dynamic_kernel(x))


def test_band_index_conventions():
    circular = band_index(4, "circular")
    assert circular.tolist() == [[0, 1, 2, 3], [3, 0, 1, 2], [2, 3, 0, 1], [1, 2, 3, 0]]
    zeros = band_index(4, "zeros")  # 4 points at the appended zero
    assert zeros.tolist() == [[0, 1, 2, 3], [4, 0, 1, 2], [4, 4, 0, 1], [4, 4, 4, 0]]


@pytest.mark.parametrize("padding", PADDINGS)
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_functional_matches_roll_and_concatenation_references(direction, padding):
    generator = torch.Generator().manual_seed(2)
    x = torch.randn(SHAPE, generator=generator, dtype=torch.float64)
    per_sample = torch.randn(SHAPE[0], SHAPE[1], _length(direction), generator=generator, dtype=torch.float64)
    out = direction_aware_conv(x, per_sample, direction, padding)
    torch.testing.assert_close(out, _roll_reference(x, per_sample, direction, padding))
    torch.testing.assert_close(out, _concat_reference(x, per_sample, direction, padding))
    shared = per_sample[0]  # a (C, L) kernel broadcasts over the batch
    torch.testing.assert_close(
        direction_aware_conv(x, shared, direction, padding), _roll_reference(x, shared, direction, padding)
    )


@pytest.mark.parametrize("direction", DIRECTIONS)
def test_the_exported_graphs_row_gather_builds_the_same_band(direction, monkeypatch):
    generator = torch.Generator().manual_seed(3)
    x = torch.randn(SHAPE, generator=generator)
    per_sample = torch.randn(SHAPE[0], SHAPE[1], _length(direction), generator=generator)
    eager = [direction_aware_conv(x, kernel, direction) for kernel in (per_sample, per_sample[0])]
    monkeypatch.setattr(torch.onnx, "is_in_onnx_export", lambda: True)
    for kernel, expected in zip((per_sample, per_sample[0]), eager, strict=True):
        assert torch.equal(direction_aware_conv(x, kernel, direction), expected)


@pytest.mark.parametrize("padding", PADDINGS)
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_module_with_known_static_kernel(direction, padding):
    dac = _dac(direction, padding).double()
    _freeze_dynamic_part(dac)
    known = torch.arange(SHAPE[1] * _length(direction), dtype=torch.float64).reshape(SHAPE[1], -1) / 10 - 0.7
    with torch.no_grad():
        dac.kernel.copy_(known)
        dac.pos_embed.zero_()
        dac.bias.zero_()
    x = torch.randn(SHAPE, dtype=torch.float64)
    torch.testing.assert_close(dac(x), _roll_reference(x, known, direction, padding))


@pytest.mark.parametrize("padding", PADDINGS)
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_module_end_to_end_equation(direction, padding):
    """``out = conv(x + PE; K_base + g(P(x))) + b`` with every part active."""
    dac = _dac(direction, padding).double()
    with torch.no_grad():
        torch.nn.init.normal_(dac.mlp[2].weight, std=0.5)
        torch.nn.init.normal_(dac.pos_embed)
        torch.nn.init.normal_(dac.bias)
    x = torch.randn(SHAPE, dtype=torch.float64)
    kernel = dac.kernel + dac.mlp(x.mean(3 if direction == "v" else 2))
    expected = _roll_reference(x + dac.pos_embed, kernel, direction, padding) + dac.bias[:, None, None]
    torch.testing.assert_close(dac(x), expected)


def test_initial_kernel_is_close_to_the_static_base():
    dac = DirectionAwareConv(16, 12, "v")
    x = torch.randn(2, 16, 12, 8) * 3
    dynamic = dac.dynamic_kernel(x) - dac.kernel
    assert 0 < dynamic.norm() / dac.kernel.norm() < 0.2


@pytest.mark.parametrize("direction", DIRECTIONS)
def test_gradients_reach_every_parameter(direction):
    dac = _dac(direction)
    x = torch.randn(SHAPE, requires_grad=True)
    (dac(x) ** 2).sum().backward()
    names = {name for name, _ in dac.named_parameters()}
    assert names == {"kernel", "pos_embed", "bias", "mlp.0.weight", "mlp.0.bias", "mlp.2.weight", "mlp.2.bias"}
    for name, parameter in dac.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
        assert parameter.grad.abs().sum() > 0, name
    assert x.grad is not None and x.grad.abs().sum() > 0


@pytest.mark.parametrize("padding", PADDINGS)
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_gradcheck_float64(direction, padding):
    shape = (2, 2, 3, 4)
    dac = _dac(direction, padding, shape).double()
    with torch.no_grad():
        torch.nn.init.normal_(dac.mlp[2].weight, std=0.5)
    names = [name for name, _ in dac.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_() for _, p in dac.named_parameters())
    x = torch.randn(shape, dtype=torch.float64, requires_grad=True)

    def run(inputs, *values):
        return functional_call(dac, dict(zip(names, values, strict=True)), (inputs,))

    assert torch.autograd.gradcheck(run, (x, *params))


def test_wrong_sizes_raise():
    with pytest.raises(ValueError, match=r"H \(dim 2\) = length = 5, got 6"):
        DirectionAwareConv(3, 5, "v")(torch.zeros(1, 3, 6, 5))
    with pytest.raises(ValueError, match=r"W \(dim 3\) = length = 7, got 5"):
        DirectionAwareConv(3, 7, "h")(torch.zeros(1, 3, 7, 5))
    with pytest.raises(ValueError, match="expects 3 channels, got 4"):
        DirectionAwareConv(3, 5, "v")(torch.zeros(1, 4, 5, 5))
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        DirectionAwareConv(3, 5, "v")(torch.zeros(3, 5, 5))
    with pytest.raises(ValueError, match="direction"):
        DirectionAwareConv(3, 5, "x")
    with pytest.raises(ValueError, match="padding"):
        DirectionAwareConv(3, 5, "v", padding="reflect")
    with pytest.raises(ValueError, match="L = x.shape"):
        direction_aware_conv(torch.zeros(1, 3, 5, 4), torch.zeros(1, 3, 4), "v")


def test_parameter_counts():
    # kernel C L + encoding C L + bias C + MLP (L h + h + h L + L), h = L / 2
    assert count_parameters(DirectionAwareConv(256, 32, "v")) == 2 * 256 * 32 + 256 + (2 * 32 * 16 + 16 + 32)
    assert count_parameters(DirectionAwareConv(256, 32, "h")) == 17712
    assert count_parameters(DirectionAwareConv(64, 200, "v")) == 65964


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::UserWarning")
@pytest.mark.parametrize("direction", DIRECTIONS)
def test_onnx_export_opset17_matches_onnxruntime(direction, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    onnx = pytest.importorskip("onnx")
    dac = _dac(direction).eval()
    with torch.no_grad():
        torch.nn.init.normal_(dac.mlp[2].weight, std=0.5)
        torch.nn.init.normal_(dac.bias)
    path = tmp_path / f"dac_{direction}.onnx"
    x = torch.randn(SHAPE)
    # The TorchScript exporter writes opset 17 as asked; the torch.export-based one (dynamo=True) only emits
    # opset >= 18 and fails to down-convert this graph (ReduceMean's axes input).
    torch.onnx.export(
        dac, (x,), str(path), opset_version=17, dynamo=False, input_names=["x"], output_names=["y"],
        dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}},
    )  # fmt: skip
    model = onnx.load(str(path))
    assert model.opset_import[0].version == 17
    assert {"Gather", "MatMul"} <= {node.op_type for node in model.graph.node}
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for batch in (SHAPE[0], 3):  # the batch stays dynamic
        inputs = torch.randn(batch, *SHAPE[1:])
        with torch.no_grad():
            expected = dac(inputs).numpy()
        np.testing.assert_allclose(session.run(None, {"x": inputs.numpy()})[0], expected, atol=1e-4, rtol=1e-4)


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::UserWarning", "ignore::FutureWarning")
def test_onnx_export_torch_export_based_opset18(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    dac = _dac("v", "zeros").eval()
    path = tmp_path / "dac.onnx"
    batch = torch.export.Dim("batch", min=1, max=64)
    torch.onnx.export(
        dac, (torch.randn(SHAPE),), str(path), opset_version=18, dynamo=True, input_names=["x"], output_names=["y"],
        dynamic_shapes={"x": {0: batch}}, verbose=False,
    )  # fmt: skip
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    inputs = torch.randn(3, *SHAPE[1:])
    with torch.no_grad():
        expected = dac(inputs).numpy()
    np.testing.assert_allclose(session.run(None, {"x": inputs.numpy()})[0], expected, atol=1e-4, rtol=1e-4)
