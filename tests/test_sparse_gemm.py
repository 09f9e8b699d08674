"""occkit's gather-GEMM sparse convolutions against spconv: the same outputs and gradients, layer by layer and for the
whole LiDAR encoder, and a backward pass that repeats bitwise."""

from __future__ import annotations

import pytest
import torch

from occkit.models.lidar_encoder import SparseEncoder
from occkit.models.sparse import SparseConv3d, SubMConv3d, sparse_tensor_from_voxels
from occkit.models.sparse_gemm import SiteIndex, build_neighbour_tables, gather_gemm_conv, neighbour_table
from occkit.models.sparse_rules import ConvSpec, build_rulebooks


def random_sites(shape: tuple[int, int, int], num: int, batch_size: int, seed: int) -> torch.Tensor:
    """``(V, 4)`` unique (batch, x, y, z) sites, clustered like a LiDAR surface: a few dense slabs plus scatter."""
    generator = torch.Generator().manual_seed(seed)
    cells = batch_size * shape[0] * shape[1] * shape[2]
    keys = torch.randperm(cells, generator=generator)[:num]
    z = keys % shape[2]
    y = keys // shape[2] % shape[1]
    x = keys // (shape[2] * shape[1]) % shape[0]
    b = keys // (shape[2] * shape[1] * shape[0])
    return torch.stack((b, x, y, z), dim=1)


def assert_close_to_scale(actual: torch.Tensor, expected: torch.Tensor, tolerance: float = 1e-5, name: str = ""):
    """``max |actual - expected| <= tolerance * max |expected|``: float32 sums in another order, nothing more."""
    error = float((actual - expected).abs().max())
    scale = float(expected.abs().max())
    assert error <= tolerance * scale, f"{name}: {error:.3g} > {tolerance:g} x {scale:.3g}"


def spconv_layer(conv, features, coords, shape, batch_size):
    return conv(sparse_tensor_from_voxels(features, coords, shape, batch_size))


#: (name, module, input shape): the encoder's layer kinds, at small sizes.
LAYERS = [
    ("submanifold 3x3x3", lambda c_in, c_out: SubMConv3d(c_in, c_out, 3, padding=1, bias=False, indice_key="s"),
     (9, 11, 7)),
    ("stride 2, padding 1", lambda c_in, c_out: SparseConv3d(c_in, c_out, 3, stride=2, padding=1, bias=False),
     (9, 11, 7)),
    ("stride 2, padding (1, 1, 0)",
     lambda c_in, c_out: SparseConv3d(c_in, c_out, 3, stride=2, padding=(1, 1, 0), bias=False), (10, 8, 6)),
    ("conv_out (1, 1, 3) stride (1, 1, 2)",
     lambda c_in, c_out: SparseConv3d(c_in, c_out, (1, 1, 3), stride=(1, 1, 2), bias=False), (6, 5, 5)),
]


@pytest.mark.parametrize("name, make, shape", LAYERS, ids=[layer[0] for layer in LAYERS])
@pytest.mark.parametrize("channels", [(5, 16), (32, 32)])
def test_layer_matches_spconv_forward_and_backward(name, make, shape, channels):
    torch.manual_seed(0)
    conv = make(*channels)
    batch_size = 2
    coords = random_sites(shape, 150, batch_size, seed=1)
    features = torch.randn(coords.shape[0], channels[0], requires_grad=True)
    expected = spconv_layer(conv, features, coords, shape, batch_size)
    grad = torch.randn_like(expected.features)
    expected_features, expected_weight = torch.autograd.grad(expected.features, (features, conv.weight), grad)

    kernel, stride, padding = (tuple(int(v) for v in getattr(conv, a)) for a in ("kernel_size", "stride", "padding"))
    out_shape = shape if conv.subm else tuple(expected.spatial_shape)
    spec = ConvSpec("k", bool(conv.subm), kernel, (1, 1, 1) if conv.subm else stride,
                    tuple(k // 2 for k in kernel) if conv.subm else padding, shape, out_shape)
    table = neighbour_table(coords, spec, batch_size)
    out = gather_gemm_conv(features, conv.weight, table)
    # The output sites as spconv lists them, matched by their coordinates.
    order = {tuple(site): row for row, site in enumerate(table.out_coords.tolist())}
    rows = torch.tensor([order[tuple(site)] for site in expected.indices.long().tolist()])
    assert len(order) == expected.indices.shape[0]
    torch.testing.assert_close(out[rows], expected.features, atol=1e-5, rtol=1e-5)
    got_features, got_weight = torch.autograd.grad(out[rows], (features, conv.weight), grad)
    torch.testing.assert_close(got_features, expected_features, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(got_weight, expected_weight, atol=1e-5, rtol=1e-5)


def test_tables_hold_the_rulebooks_pairs():
    """Every (input, output, offset) pair of the export path's rulebooks is in the neighbour tables, and no other."""
    encoder = SparseEncoder(4, (24, 24, 21), encoder_channels=((16, 32), (32, 64), (64,)),
                            downsample_paddings=((1, 1, 1), (1, 1, 0)))  # fmt: skip
    coords = random_sites(encoder.sparse_shape, 400, 2, seed=3)
    tables = build_neighbour_tables(encoder.conv_specs, coords, 2)
    rulebooks = build_rulebooks(encoder.conv_specs, coords)
    for spec in encoder.conv_specs:
        table, rulebook = tables[spec.key], rulebooks[spec.key]
        torch.testing.assert_close(table.out_coords, rulebook.out_coords)
        listed = set()
        for column, offset in enumerate(spec.offsets):
            inputs, outputs = rulebook.pairs[:, column]
            listed |= {(i, o, offset) for i, o in zip(inputs.tolist(), outputs.tolist(), strict=True)
                       if o < rulebook.num_out}
        if spec.subm:  # the rulebook leaves the centre out: it pairs every site with itself
            listed |= {(i, i, spec.centre) for i in range(table.table.shape[0])}
        found = {(i, o, k) for o, row in enumerate(table.table.tolist()) for k, i in enumerate(row)
                 if i < table.transposed.shape[0]}  # fmt: skip
        assert found == listed, spec.key
        transposed = {(i, o, k) for i, row in enumerate(table.transposed.tolist()) for k, o in enumerate(row)
                      if o < table.table.shape[0]}  # fmt: skip
        assert transposed == found, spec.key


def make_encoder(seed: int = 0) -> tuple[SparseEncoder, torch.Tensor, torch.Tensor]:
    torch.manual_seed(seed)
    encoder = SparseEncoder(5, (32, 32, 21), encoder_channels=((16, 16, 32), (32, 32, 64), (64, 64)),
                            downsample_paddings=((1, 1, 1), (1, 1, 0)))  # fmt: skip
    coords = random_sites(encoder.sparse_shape, 900, 2, seed=seed + 1)
    features = torch.randn(coords.shape[0], 5)
    return encoder.train(), features, coords


def _encoder_pass(encoder: SparseEncoder, features: torch.Tensor, coords: torch.Tensor, backend: str,
                  dtype: torch.dtype) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The BEV of one training pass of ``encoder`` in ``dtype`` and every parameter's gradient (float64)."""
    encoder.to(dtype).backend = backend
    encoder.zero_grad()
    bev = encoder(features.to(dtype), coords, 2)
    (bev * torch.linspace(-1, 1, bev.numel(), dtype=dtype).view_as(bev)).sum().backward()
    return bev.detach().double(), {n: p.grad.double() for n, p in encoder.named_parameters()}


def test_encoder_matches_spconv_in_training():
    """Forward (BatchNorm on batch statistics) and every parameter's gradient, gather-GEMM against spconv.

    In float64 the two agree to rounding: the same sums. In float32 each backend's gradients lie within 1.1e-5 of
    the float64 ones (at one thread or two), and so within about twice that of each other: BatchNorm on the batch
    statistics of a few hundred sites amplifies the rounding of the sums before it, whichever order they take. The
    BEV itself agrees to 1e-5 in float32."""
    encoder, features, coords = make_encoder()
    exact = {backend: _encoder_pass(encoder, features, coords, backend, torch.float64)
             for backend in ("spconv", "gather_gemm")}  # fmt: skip
    (bev_spconv, grads_spconv), (bev_gemm, grads_gemm) = exact["spconv"], exact["gather_gemm"]
    assert bev_gemm.shape == bev_spconv.shape == (2, 128 * 2, 8, 8)  # conv_out: 128 channels x 2 heights
    assert_close_to_scale(bev_gemm, bev_spconv, tolerance=1e-12, name="BEV")
    for name, grad in grads_spconv.items():
        assert_close_to_scale(grads_gemm[name], grad, tolerance=1e-12, name=name)
    for backend in ("spconv", "gather_gemm"):
        bev, grads = _encoder_pass(encoder, features, coords, backend, torch.float32)
        assert_close_to_scale(bev, bev_spconv, name=f"{backend} BEV, float32")
        for name, grad in grads_spconv.items():
            assert_close_to_scale(grads[name], grad, tolerance=2e-5, name=f"{backend} {name}, float32")


def test_auto_backend_is_gather_gemm_on_the_cpu_and_the_backward_repeats_bitwise():
    encoder, features, coords = make_encoder(seed=4)
    assert encoder.backend == "auto"
    grads = []
    for _ in range(2):
        encoder.zero_grad()
        encoder(features, coords, 2).square().sum().backward()
        grads.append([p.grad.clone() for p in encoder.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))
    encoder.backend = "spconv"
    encoder.zero_grad()
    encoder(features, coords, 2).square().sum().backward()
    assert_close_to_scale(grads[0][0], next(encoder.parameters()).grad)


def test_unknown_backend_and_mismatched_rows_are_refused():
    encoder, features, coords = make_encoder()
    encoder.backend = "dense"
    with pytest.raises(ValueError, match="sparse backend must be one of auto, spconv, gather_gemm, got 'dense'"):
        encoder(features, coords, 2)
    table = build_neighbour_tables(encoder.conv_specs, coords, 2)["subm1"]
    with pytest.raises(ValueError, match="features have 3 rows but the table lists"):
        gather_gemm_conv(features[:3], encoder.conv_input[0].weight, table)


def test_site_index_finds_neighbours_at_the_grid_edges_and_across_samples():
    coords = torch.tensor([[0, 0, 0, 0], [0, 0, 0, 1], [0, 3, 2, 4], [1, 0, 0, 0]])
    index = SiteIndex(coords, (4, 3, 5), batch_size=2, halo=(1, 1, 1))
    delta = torch.tensor([[0, 0, -1], [0, 0, 0], [0, 0, 1]])
    rows = index.neighbours(coords, delta)
    # site 0 sees site 1 above it; site 1 sees site 0 below; the corner site 2 sees only itself; the other sample's
    # site 3, at the same (x, y, z) as site 0, never sees sample 0's sites.
    assert rows.tolist() == [[-1, 0, 1], [0, 1, -1], [-1, 2, -1], [-1, 3, -1]]
