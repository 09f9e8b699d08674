"""The inference fast path: a trained model turned into the fastest equivalent network for deployment.

Each step is optional, because whether it pays depends on the device (``occkit bench`` measures every one and
keeps the ones that speed the model up; see ``docs/benchmarks.md``):

``fixed_calibration``
    The model computes its plan once and reuses it (:mod:`occkit.models.base`): LSS's pooling ranks, the
    projection's sampling grids, the BVRE grid, DA-Occ's two pooling plans and camera parameters. Valid for one rig
    without test-time augmentation, as the papers time them.
``fold_bn``
    Every ``BatchNorm2d`` that directly consumes a ``Conv2d``'s output is folded into that convolution
    (``w' = w * g / sqrt(v + eps)``, ``b' = (b - m) * g / sqrt(v + eps) + beta``) and replaced by ``Identity``.
``channels_last``
    Convolution weights in NHWC order, so convolutions run in the layout oneDNN and cuDNN prefer.
``compile``
    ``torch.compile`` on the forward of each dense stage (every child module without sparse convolutions), so
    hooks on the stages keep working and spconv stays eager.
``cuda_graph``
    The network (:meth:`~occkit.models.base.OccupancyModel.network`) captured as a CUDA graph and replayed
    (:mod:`occkit.models.cuda_graph`): at batch 1 a GPU pass is bound by its hundreds of kernel launches, which a
    replay issues in one call. CUDA only. DAOcc's sparse LiDAR encoder runs eagerly (spconv builds its rulebooks on
    the host) while its camera branch replays from a graph on a side stream; the fusion and heads replay after.

Always done: eval mode and the detection branch removed (it runs only in training).

    >>> model = prepare_for_inference(zoo.build("flashocc_tiny"), ("fixed_calibration", "fold_bn"))  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Iterator, Sequence

import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from occkit.models.base import OccupancyModel
from occkit.models.cuda_graph import NetworkGraphs
from occkit.models.sparse import spconv

__all__ = [
    "OPTIMIZATIONS",
    "check_optimizations",
    "prepare_for_inference",
    "apply_optimization",
    "fix_calibration",
    "fold_conv_bn",
    "to_channels_last",
    "compile_dense_stages",
    "capture_cuda_graphs",
    "eager_network",
    "has_sparse_convolutions",
    "graphed_sparse_convolutions",
]

#: The optional steps, in the order they are applied.
OPTIMIZATIONS = ("fixed_calibration", "fold_bn", "channels_last", "compile", "cuda_graph")


def check_optimizations(names: Sequence[str]) -> tuple[str, ...]:
    """``names`` validated and put in :data:`OPTIMIZATIONS` order (compile after the weight rewrites: it must see the
    final weights; the CUDA graphs last: they capture whatever the network has become)."""
    unknown = sorted(set(names) - set(OPTIMIZATIONS))
    if unknown:
        raise ValueError(f"unknown optimization(s) {', '.join(unknown)}; choose from {', '.join(OPTIMIZATIONS)}")
    return tuple(name for name in OPTIMIZATIONS if name in names)


def prepare_for_inference(model: nn.Module, optimizations: Sequence[str] = ()) -> nn.Module:
    """Eval mode, detection branch removed, then ``optimizations`` applied in :data:`OPTIMIZATIONS` order.

    Modifies ``model`` in place (folding rewrites its weights) and returns it.
    """
    model.eval()
    if getattr(model, "detection_head", None) is not None:
        model.remove_detection()
    for name in check_optimizations(optimizations):
        apply_optimization(model, name)
    return model


def apply_optimization(model: nn.Module, name: str) -> None:
    """Apply one step of :data:`OPTIMIZATIONS` to an eval-mode ``model`` in place."""
    steps = {
        "fixed_calibration": fix_calibration,
        "fold_bn": fold_conv_bn,
        "channels_last": to_channels_last,
        "compile": compile_dense_stages,
        "cuda_graph": capture_cuda_graphs,
    }
    if name not in steps:
        raise ValueError(f"unknown optimization {name!r}; choose from {', '.join(OPTIMIZATIONS)}")
    steps[name](model)


# ------------------------------------------------------------------------------------------- fixed calibration
def fix_calibration(model: nn.Module) -> list[str]:
    """Let every occupancy model in ``model`` reuse its plan in eval mode; the names of those models.

    The plan (:mod:`occkit.models.base`: pooling ranks, sampling grids, camera parameters) is then computed at the
    first forward and reused while the batch and image sizes stay the same; the network code is unchanged.
    """
    changed = []
    for name, module in model.named_modules():
        if isinstance(module, OccupancyModel):
            module.reuse_plan = True
            changed.append(name or type(module).__name__)
    return changed


# ------------------------------------------------------------------------------------------------- BN folding
def _conv_bn_pairs(module: nn.Module) -> list[tuple[str, str]] | None:
    """``(conv, bn)`` submodule paths where ``module``'s forward feeds a ``Conv2d`` output only to a ``BatchNorm2d``.

    None when the forward cannot be traced symbolically (data-dependent control flow, non-tensor inputs such as a
    :class:`~occkit.types.Batch`); the caller then looks at the children, whose forwards are simpler.
    """
    try:
        graph = torch.fx.Tracer().trace(module)
    except Exception:  # noqa: BLE001 -- tracing is a probe: any failure only means "not traceable as a whole"
        return None
    calls = Counter(node.target for node in graph.nodes if node.op == "call_module")
    pairs = []
    for node in graph.nodes:
        if node.op != "call_module" or not isinstance(module.get_submodule(node.target), nn.BatchNorm2d):
            continue
        source = node.args[0] if len(node.args) == 1 and not node.kwargs else None
        if (
            isinstance(source, torch.fx.Node)
            and source.op == "call_module"
            and type(module.get_submodule(source.target)) is nn.Conv2d
            and len(source.users) == 1  # the un-normalised output is used nowhere else
            and calls[source.target] == calls[node.target] == 1  # each module runs once, so folding changes only this
        ):
            pairs.append((source.target, node.target))
    return pairs


def _has_batch_norm(module: nn.Module) -> bool:
    return any(isinstance(m, nn.BatchNorm2d) for m in module.modules())


def _replace(root: nn.Module, path: str, new: nn.Module) -> None:
    parent, _, name = path.rpartition(".")
    setattr(root.get_submodule(parent), name, new)


def fold_conv_bn(model: nn.Module) -> list[str]:
    """Fold every ``BatchNorm2d`` that directly follows a ``Conv2d`` into it; the paths of the folded BatchNorms.

    The pairs are found from the data flow, not from names or positions: the largest submodules whose forward
    ``torch.fx`` can trace are traced, and a BatchNorm is folded when its only input is a convolution's output that
    nothing else reads, both modules running once there and appearing once in the whole model (shared modules are
    left alone). This finds ``Sequential(conv, bn, relu)`` and torchvision's ``conv1``/``bn1`` attribute pairs alike.
    BatchNorms after other layers (DA-Occ's direction-aware convolutions, spconv's BatchNorm1d) stay as they are.

    Raises:
        ValueError: ``model`` is in training mode (folding uses the running statistics).
    """
    if model.training:
        raise ValueError("fold_conv_bn needs an eval-mode model (folding uses the BatchNorm running statistics)")
    occurrences = Counter(id(m) for _, m in model.named_modules(remove_duplicate=False))
    folded: list[str] = []

    def visit(module: nn.Module, prefix: str) -> None:
        if not _has_batch_norm(module):
            return
        pairs = _conv_bn_pairs(module) if not isinstance(module, nn.BatchNorm2d) else []
        if pairs is None:
            for name, child in module.named_children():
                visit(child, f"{prefix}{name}.")
            return
        for conv_path, bn_path in pairs:
            conv, bn = module.get_submodule(conv_path), module.get_submodule(bn_path)
            if occurrences[id(conv)] != 1 or occurrences[id(bn)] != 1 or not bn.track_running_stats:
                continue
            _replace(module, conv_path, fuse_conv_bn_eval(conv, bn))
            _replace(module, bn_path, nn.Identity())
            folded.append(prefix + bn_path)

    visit(model, "")
    return folded


# ---------------------------------------------------------------------------------------- layout and compile
def to_channels_last(model: nn.Module) -> list[str]:
    """Weights of every ``Conv2d`` in channels-last order; the names of those convolutions.

    A convolution with a channels-last weight returns a channels-last output, so the layout propagates through each
    dense stage without converting the inputs. (``model.to(memory_format=...)`` would also try the 5-D weights of the
    sparse convolutions, which have no channels-last order.)
    """
    converted = []
    for name, module in model.named_modules():
        if isinstance(module, nn.Conv2d):
            module.weight.data = module.weight.data.contiguous(memory_format=torch.channels_last)
            converted.append(name)
    return converted


def has_sparse_convolutions(module: nn.Module) -> bool:
    """Whether ``module`` holds spconv layers (which neither ``compile`` nor ``cuda_graph`` takes)."""
    return any(isinstance(m, spconv.SparseModule) for m in module.modules())


def compile_dense_stages(model: nn.Module) -> list[str]:
    """``torch.compile`` the forward of every direct child with parameters and no sparse convolution; their names.

    Compiling the forward (not the module) keeps the module's hooks outside the compiled graph. Inductor runs with
    ``freezing``: weights become constants, which lets it fold them and prepack convolution weights for inference.
    CUDA graphs are the separate ``cuda_graph`` step, which then replays the compiled kernels. Compilation happens at
    the first call; on a CPU it needs a C++ compiler.
    """
    compiled = []
    for name, child in model.named_children():
        if next(child.parameters(), None) is None or has_sparse_convolutions(child):
            continue
        child.forward = torch.compile(child.forward, options={"freezing": True, "triton.cudagraphs": False})
        compiled.append(name)
    return compiled


def graphed_sparse_convolutions(model: nn.Module) -> bool:
    """Whether a CUDA graph of ``model``'s networks would have to capture spconv layers: those outside every
    occupancy model's :meth:`~occkit.models.base.OccupancyModel.eager_stages` (spconv builds its rulebooks on the
    host, which a graph cannot capture)."""
    eager = {id(layer) for module in model.modules() if isinstance(module, OccupancyModel)
             for stage in module.eager_stages() for layer in module.get_submodule(stage).modules()}  # fmt: skip
    return any(isinstance(m, spconv.SparseModule) and id(m) not in eager for m in model.modules())


def capture_cuda_graphs(model: nn.Module) -> list[str]:
    """Let every occupancy model in ``model`` replay its network from CUDA graphs in eval mode
    (:mod:`occkit.models.cuda_graph`), its :meth:`~occkit.models.base.OccupancyModel.eager_stages` (DAOcc's sparse
    LiDAR encoder) run eagerly outside them; the names of those models.

    Raises:
        ValueError: ``model`` is not on a CUDA device, or the graph would have to capture sparse convolutions
            (:func:`graphed_sparse_convolutions`).
    """
    if graphed_sparse_convolutions(model):
        raise ValueError("cuda_graph cannot capture sparse convolutions (spconv builds its rulebooks on the host) and "
                         "this network needs them inside its graph")  # fmt: skip
    parameter = next(model.parameters(), None)
    if parameter is None or parameter.device.type != "cuda":
        raise ValueError("cuda_graph needs a model on a CUDA device")
    changed = []
    for name, module in model.named_modules():
        if isinstance(module, OccupancyModel):
            module.network_graphs = NetworkGraphs()
            changed.append(name or type(module).__name__)
    return changed


@contextlib.contextmanager
def eager_network(model: nn.Module) -> Iterator[None]:
    """Inside the block, ``model``'s networks run eagerly (a CUDA graph replays without calling the modules, so
    forward hooks, such as the benchmark's stage timers, see nothing)."""
    saved = {module: module.network_graphs for module in model.modules() if isinstance(module, OccupancyModel)}
    for module in saved:
        module.network_graphs = None
    try:
        yield
    finally:
        for module, graphs in saved.items():
            module.network_graphs = graphs
