"""A model's network replayed as a CUDA graph: every kernel of a pass launched in one call.

At batch 1 the paper models are bound by kernel launches on a GPU (hundreds of small kernels, each a few
microseconds of CPU work), not by arithmetic. :class:`NetworkGraphs` captures
:meth:`~occkit.models.base.OccupancyModel.network` (a function of tensors only: the frame's inputs, a temporal model's
history inputs, and the plan's tensors) once per input signature, and then copies each call's tensors into the
captured ones and replays the graph. The plan, the history memory and the prediction stay eager around it.

Captured once per signature: the inputs' and the plan's tensor names, shapes, dtypes and devices, the plan's
non-tensor fields, and the autocast state. A call with a plan tensor of another shape (a new rig under
``fixed_calibration`` off, a new batch size) captures a new graph; one in training mode, with gradients enabled or
on CPU tensors runs the network eagerly.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor

from occkit.models.plans import plan_tensors, plan_with_tensors

__all__ = ["NetworkGraphs", "clone_tensors", "side_stream"]

Network = Callable[[Mapping[str, Tensor], Any], Any]

#: Eager passes on a side stream before a capture, as PyTorch prescribes (lazy initialisation, cuDNN's algorithm
#: search and inductor's compilation then happen outside the graph).
WARMUP_PASSES = 2


class NetworkGraphs:
    """The CUDA graphs of one model's network, by input signature (module docstring); called in its place.

    A copy of a model (``copy.deepcopy``, pickling) starts without graphs: a graph holds the memory of the model it was
    captured from.
    """

    def __init__(self) -> None:
        self._graphs: dict[tuple, _CapturedNetwork] = {}
        # The last plan's non-tensor description: a reused plan (fixed_calibration) is described once, not per call.
        self._plan: Any = None
        self._plan_fields = ""

    def __deepcopy__(self, memo: dict) -> NetworkGraphs:
        return NetworkGraphs()

    def __getstate__(self) -> dict:
        return {}

    def __setstate__(self, state: dict) -> None:
        self.__init__()

    def __len__(self) -> int:
        """Graphs captured so far."""
        return len(self._graphs)

    def __call__(self, network: Network, inputs: Mapping[str, Tensor], plan: Any) -> Any:
        """``network(inputs, plan)``, from a graph when every tensor is on CUDA and no gradient is recorded."""
        tensors = _named_tensors(inputs, plan)
        if torch.is_grad_enabled() or not tensors or not all(t.is_cuda for t in tensors.values()):
            return network(inputs, plan)
        if plan is not self._plan:
            self._plan, self._plan_fields = plan, _plan_fields(plan, tensors)
        key = _signature(inputs, tensors, self._plan_fields)
        graph = self._graphs.get(key)
        if graph is None:
            graph = self._graphs[key] = _CapturedNetwork(network, inputs, plan, tensors)
        return graph.replay(tensors)


class _CapturedNetwork:
    """One capture: static copies of the call's tensors, the graph, and its (static) outputs."""

    def __init__(self, network: Network, inputs: Mapping[str, Tensor], plan: Any,
                 tensors: dict[str, Tensor]) -> None:  # fmt: skip
        self.static = {name: tensor.clone() for name, tensor in tensors.items()}
        # A reused plan (fixed_calibration) passes the same tensors every call: they are not copied again.
        self.sources = {name: tensor for name, tensor in tensors.items() if name.startswith("plan.")}
        static_inputs = {name: self.static.get(f"inputs.{name}", value) for name, value in inputs.items()}
        static_plan = plan_with_tensors(
            plan,
            {name.removeprefix("plan."): tensor for name, tensor in self.static.items() if name.startswith("plan.")},
        )
        device = next(iter(tensors.values())).device
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(WARMUP_PASSES):
                network(static_inputs, static_plan)
        torch.cuda.current_stream(device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        # Autocast's cache of cast weights lives only as long as the caller's autocast block; a graph that read it
        # would read freed memory at the next replay, so the capture casts inside the graph instead.
        autocast = torch.autocast("cuda", dtype=torch.get_autocast_dtype("cuda"),
                                  enabled=torch.is_autocast_enabled("cuda"), cache_enabled=False)  # fmt: skip
        with autocast, torch.cuda.graph(self.graph):
            self.output = network(static_inputs, static_plan)

    def replay(self, tensors: dict[str, Tensor]) -> Any:
        """The call's tensors copied into the captured ones, the graph replayed, and its outputs cloned (the next
        replay overwrites them)."""
        for name, tensor in tensors.items():
            if self.sources.get(name) is not tensor:
                self.static[name].copy_(tensor)
        self.graph.replay()
        return clone_tensors(self.output)


@functools.cache
def side_stream(device: torch.device) -> torch.cuda.Stream:
    """A second stream of ``device``, one per process: where a model replays a graph beside eager work on the current
    stream (DAOcc's camera branch beside its sparse LiDAR encoder)."""
    return torch.cuda.Stream(device)


def _named_tensors(inputs: Mapping[str, Tensor], plan: Any) -> dict[str, Tensor]:
    named = {f"inputs.{name}": value for name, value in inputs.items() if isinstance(value, Tensor)}
    named.update({f"plan.{name}": value for name, value in plan_tensors(plan).items()})
    return named


def _plan_fields(plan: Any, tensors: dict[str, Tensor]) -> str:
    """The plan's non-tensor fields (its tensors left out), as text."""
    names = [name.removeprefix("plan.") for name in tensors if name.startswith("plan.")]
    return repr(plan_with_tensors(plan, dict.fromkeys(names)))


def _signature(inputs: Mapping[str, Tensor], tensors: dict[str, Tensor], plan_fields: str) -> tuple:
    layout = tuple((name, tuple(t.shape), t.dtype, t.device, t.stride()) for name, t in tensors.items())
    others = tuple((name, repr(value)) for name, value in inputs.items() if not isinstance(value, Tensor))
    autocast = (torch.is_autocast_enabled("cuda"), torch.get_autocast_dtype("cuda"))
    return layout, others, plan_fields, autocast


def clone_tensors(value: Any) -> Any:
    """``value`` with every tensor in it (through dicts, lists, tuples, named tuples and dataclasses) cloned."""
    if isinstance(value, Tensor):
        return value.clone()
    if isinstance(value, dict):
        return type(value)((key, clone_tensors(item)) for key, item in value.items())
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value)(*(clone_tensors(item) for item in value))
    if isinstance(value, (list, tuple)):
        return type(value)(clone_tensors(item) for item in value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {f.name: clone_tensors(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init}
        return dataclasses.replace(value, **fields)
    return value
