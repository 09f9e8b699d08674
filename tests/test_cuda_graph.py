"""The ``cuda_graph`` fast-path step (occkit.models.cuda_graph): what a CPU can check of it, that the camera
networks and DAOcc's network after its sparse encoder make no host synchronisation a graph capture would refuse, and
graph against eager on CUDA."""

from __future__ import annotations

import copy
import dataclasses
from typing import NamedTuple

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from occkit import zoo
from occkit.models.base import OccupancyModel
from occkit.models.cuda_graph import NetworkGraphs, clone_tensors
from occkit.models.inference import (
    capture_cuda_graphs,
    eager_network,
    graphed_sparse_convolutions,
    prepare_for_inference,
)

aten = torch.ops.aten

#: Operators that wait for the device (their result decides a size or a Python value) or copy host data in: a CUDA
#: graph capture fails on them (or would replay a stale copy).
HOST_SYNCS = {
    aten._local_scalar_dense.default,  # .item(), bool(tensor), .tolist()
    aten.is_nonzero.default,
    aten.equal.default,
    aten.nonzero.default,
    aten.masked_select.default,
    aten.bincount.default,
    aten._unique2.default,
    aten.unique_dim.default,
    aten.unique_consecutive.default,
    aten.repeat_interleave.Tensor,
}


class HostSyncs(TorchDispatchMode):
    """Records the operators of :data:`HOST_SYNCS` that run inside it, and indexing by a boolean mask (a nonzero)."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        masked = func in (aten.index.Tensor, aten.index_put.default, aten.index_put_.default) and any(
            index is not None and index.dtype == torch.bool for index in args[1]
        )
        # torch.tensor(python data) is a host-to-device copy on CUDA; a 0-d one is a scalar argument, which is not.
        host_data = func is aten.lift_fresh.default and args[0].dim() > 0
        if func in HOST_SYNCS or masked or host_data:
            self.found.append(str(func))
        return func(*args, **kwargs)


@pytest.fixture(scope="module")
def bench_world(synthetic_world):
    """test_bench's world: one scene, two frames, 176 x 99 images."""
    return synthetic_world(scenes=1, frames=2, image_size=(176, 99))


def _tiny_batch(entry: str, world) -> object:
    from occkit.bench.sample import load_sample

    return load_sample(entry, str(world), log=lambda _: None)


@pytest.mark.parametrize("entry", ["flashocc_tiny", "da_occ_tiny", "da_occ_tiny_temporal"])
def test_the_camera_networks_make_no_host_synchronisation(entry, bench_world):
    """The network of each camera family, a temporal one streamed, runs without an operator that a CUDA graph
    capture refuses: what ``cuda_graph`` captures on a GPU (the plan and the memory stay outside)."""
    model = prepare_for_inference(zoo.build(entry), ("fixed_calibration",))
    batch = _tiny_batch(entry, bench_world)
    memory = model.stream() if model.temporal is not None else None
    network = model.network
    calls = []

    def watched(inputs, plan):
        with torch.no_grad(), HostSyncs() as mode:
            output = network(inputs, plan)
        calls.append(mode.found)
        return output

    model.network = watched
    with torch.no_grad():
        for _ in range(2):  # the second pass reuses the plan, and a temporal model reads its memory
            model(batch, memory=memory)
    assert calls == [[], []]


def test_the_checker_finds_what_a_capture_refuses():
    with HostSyncs() as mode:
        x = torch.arange(6.0)
        float(x.sum())
        x[x > 2] = 0
        torch.tensor([1.0, 2.0])
    assert mode.found == ["aten._local_scalar_dense.default", "aten.index_put_.default", "aten.lift_fresh.default"]


def test_graphs_run_the_network_eagerly_on_cpu_tensors_and_a_copy_starts_without_graphs():
    model = zoo.build("flashocc_tiny").eval()
    model.network_graphs = NetworkGraphs()
    images = torch.randn(1, 6, 3, 64, 176)
    calls = []

    def network(inputs, plan):
        calls.append(inputs["images"])
        return inputs["images"] * 2

    with torch.no_grad():
        output = model.network_graphs(network, {"images": images}, None)
    assert torch.equal(output, images * 2) and calls[0] is images and len(model.network_graphs) == 0
    copied = copy.deepcopy(model)
    assert isinstance(copied.network_graphs, NetworkGraphs) and copied.network_graphs is not model.network_graphs


def test_cuda_graph_refuses_a_cpu_model_and_sparse_convolutions_inside_the_graph():
    with pytest.raises(ValueError, match="CUDA device"):
        capture_cuda_graphs(zoo.build("flashocc_tiny").eval())
    with pytest.raises(ValueError, match="CUDA device"):  # its sparse encoder runs before the graph
        capture_cuda_graphs(zoo.build("daocc_tiny").eval())
    assert not graphed_sparse_convolutions(zoo.build("daocc_tiny"))
    # The flow head's motion input needs the points inside the network: the encoder cannot leave the graph.
    with pytest.raises(ValueError, match="sparse convolutions"):
        capture_cuda_graphs(zoo.build("daocc_tiny_flow").eval())


def test_daocc_runs_its_sparse_encoder_outside_its_graphs_and_the_rest_without_host_synchronisation(bench_world):
    """What a GPU captures of DAOcc: the camera branch, and the network from the two BEVs on (or from the LiDAR BEV
    with the images), each with the same outputs as the whole network and no operator a capture refuses; on CPU
    tensors the graphs run the network eagerly."""
    model = prepare_for_inference(zoo.build("daocc_tiny"), ("fixed_calibration",))
    batch = _tiny_batch("daocc_tiny", bench_world)
    with torch.no_grad():
        expected = model(batch).occupancy
        plan = model.current_plan(batch)
        inputs = model.graph_inputs(model.inputs(batch))
        assert model.eager_stages() == ("lidar_encoder",) and set(inputs) == {"images", "lidar_bev"}
        with HostSyncs() as mode:
            dense = model.network(inputs, plan).occupancy
            camera = model.camera_bev({"images": inputs["images"]}, plan)
            fused = model.network({**camera, "lidar_bev": inputs["lidar_bev"]}, plan).occupancy
        model.network_graphs = NetworkGraphs()
        graphed = model(batch).occupancy
    assert mode.found == []
    for output in (dense, fused, graphed):
        torch.testing.assert_close(output, expected, rtol=0, atol=0)


def test_eager_network_lifts_the_graphs_inside_its_block():
    model = zoo.build("flashocc_tiny").eval()
    graphs = model.network_graphs = NetworkGraphs()
    with eager_network(model):
        assert all(m.network_graphs is None for m in model.modules() if isinstance(m, OccupancyModel))
    assert model.network_graphs is graphs


def test_replayed_outputs_are_clones_that_a_later_replay_cannot_overwrite():
    """Every tensor of a graph's output is cloned, through containers and dataclasses: a replay rewrites the graph's
    output memory, which the tensors already returned must not share."""

    @dataclasses.dataclass
    class Output:
        logits: torch.Tensor
        extra: dict

    class Pair(NamedTuple):
        first: torch.Tensor
        second: int

    buffer = torch.ones(3)  # stands for the graph's output memory
    cloned = clone_tensors(Output(logits=buffer, extra={"pair": Pair(buffer, 2), "list": [buffer]}))
    buffer.fill_(5.0)
    assert torch.equal(cloned.logits, torch.ones(3))
    assert torch.equal(cloned.extra["pair"].first, torch.ones(3)) and cloned.extra["pair"].second == 2
    assert torch.equal(cloned.extra["list"][0], torch.ones(3))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only")
def test_daocc_replays_its_dense_network_around_the_eager_sparse_encoder(bench_world):
    model = prepare_for_inference(zoo.build("daocc_tiny").cuda(), ("fixed_calibration",))
    batch = _tiny_batch("daocc_tiny", bench_world).to("cuda")
    frames = [batch, dataclasses.replace(batch, images=batch.images.flip(-1))]
    with torch.no_grad():
        eager = [model(frame).occupancy for frame in frames]
        capture_cuda_graphs(model)
        graphed = [model(frame).occupancy for frame in frames]
    assert len(model.network_graphs) == 2  # the camera branch, and the network from the two BEVs
    for expected, replayed in zip(eager, graphed, strict=True):
        torch.testing.assert_close(replayed, expected, rtol=1e-4, atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA only")
@pytest.mark.parametrize("precision", [torch.float32, torch.float16])
def test_a_graph_replays_the_eager_network_frame_after_frame(precision, bench_world):
    model = prepare_for_inference(zoo.build("da_occ_tiny_temporal").cuda(), ("fixed_calibration",))
    batch = _tiny_batch("da_occ_tiny_temporal", bench_world).to("cuda")
    frames = [batch, dataclasses.replace(batch, images=batch.images.flip(-1))]
    autocast = torch.autocast("cuda", dtype=precision, enabled=precision != torch.float32)

    def stream():
        memory = model.stream()
        with torch.no_grad(), autocast:
            return [model(frame, memory=memory).occupancy.float() for frame in frames * 2]

    eager = stream()
    capture_cuda_graphs(model)
    graphed = stream()
    assert len(model.network_graphs) == 1
    for expected, replayed in zip(eager, graphed, strict=True):
        torch.testing.assert_close(replayed, expected, rtol=1e-3, atol=1e-3)
