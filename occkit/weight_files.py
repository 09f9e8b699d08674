"""Reading weight files without running their code: torch files loaded weights-only, and ``.safetensors``.

Checkpoints of the reference toolkits (mmcv, mmdet3d) pickle a ``meta`` dict beside the weights, which may hold numpy
scalars and arrays (an evaluation hook's scores); those reconstructors are allowed beside torch's weights-only set,
since they rebuild plain numbers and arrays and nothing callable. Anything else a file would unpickle is refused with
a message naming the file and the refused global. Before any of it, the file's declared sizes are checked
(:mod:`occkit.archives`), and after it every tensor must be a dense one with its data. The pretrained backbones
(:mod:`occkit.models.pretrained`), the checkpoint converter (:mod:`occkit.convert`) and occkit's own checkpoints
(:mod:`occkit.engine.checkpoint`) read through here; :func:`check_finite` refuses weights that are NaN or infinite.
:func:`read_checkpoint` finds the state dict in any of the checkpoint files occkit reads (mmcv's, occkit's own,
``.safetensors``, bare state dicts), without knowing any model.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from occkit.archives import check_torch_file
from occkit.arguments import format_bytes

__all__ = [
    "WEIGHTS_FORMAT",
    "ReferenceCheckpoint",
    "load_torch_file",
    "check_finite",
    "read_safetensors",
    "read_checkpoint",
    "strip_wrappers",
]

#: ``format`` in the metadata of occkit's ``.safetensors`` weights (``occkit convert``'s output, the shipped weights).
WEIGHTS_FORMAT = "occkit-weights/1"

#: How the ``format`` marker of occkit's run checkpoints (``occkit.engine.checkpoint.FORMAT``) begins. Matched by
#: prefix, not imported: the engine reads its checkpoints through this module, so this module sits below it.
_CHECKPOINT_FORMAT_PREFIX = "occkit-checkpoint/"


def _numpy_globals() -> list:
    """numpy reconstructors mmcv's ``meta`` may need (scalars from evaluation hooks, arrays), allowed beside torch's
    weights-only set: they rebuild plain numbers and arrays, nothing callable. Both module spellings, as files
    written under numpy 1 (the references' environments) name ``numpy.core`` and under numpy 2 ``numpy._core``."""
    import numpy as np

    multiarray = np._core.multiarray if hasattr(np, "_core") else np.core.multiarray
    allowed: list = [np.dtype, np.ndarray]
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed += [(multiarray.scalar, f"{module}.scalar"), (multiarray._reconstruct, f"{module}._reconstruct")]
    allowed += [type(np.dtype(name)) for name in ("float64", "float32", "float16", "int64", "int32", "bool")]
    return allowed


def load_torch_file(path: str | Path, map_location: str | torch.device = "cpu") -> Any:
    """The object a torch file holds, loaded weights-only (numpy metadata allowed) onto ``map_location``.

    Before ``torch.load`` the file's declared sizes are checked (:func:`occkit.archives.check_torch_file`), so a
    crafted archive is refused before it inflates; after it, every tensor must be dense, with its data (not a meta
    tensor, not a view larger than the data it was saved with, which would allocate its full size on first use).

    Raises:
        ValueError: the file cannot be read safely or at all (the message names the file and why; a refused
            pickle names the global it would have run).
    """
    path = Path(path)
    check_torch_file(path)
    try:
        with torch.serialization.safe_globals(_numpy_globals()), warnings.catch_warnings():
            # A sparse tensor is refused below in one line; torch's note that it validates one would be a second.
            warnings.filterwarnings("ignore", message="Validating sparse tensor invariants")
            payload = torch.load(path, map_location=map_location, weights_only=True)
    except MemoryError:
        raise
    except Exception as error:  # torch raises UnpicklingError, RuntimeError, EOFError, ... for unreadable files
        raise ValueError(_refusal(path, error)) from error
    _check_tensors(payload, path)
    return payload


#: How torch words a refused global: a module it blocks (``posix.system``), a global outside the allowed set, a
#: class or function the unpickler met another way.
_REFUSED = (re.compile(r"GLOBAL ([\w.]+)"), re.compile(r"unrecognized function (.+?)(?: which belongs|$)"),
            re.compile(r"allowlisted via `add_safe_globals` but got (.+?)$"))  # fmt: skip


def _refusal(path: Path, error: Exception) -> str:
    """One line saying why ``torch.load`` refused ``path``: the global a pickle would run, or torch's own reason
    without its advice (which would have the user unpickle code with ``weights_only=False``)."""
    text = " ".join(str(error).split())
    # torch wraps its reason in advice: from "Weights only load failed" up to the reason (after "WeightsUnpickler
    # error:" where it says so), and a pointer to its documentation after it.
    reason = text.split("WeightsUnpickler error:")[-1]
    reason = re.sub(r"Weights only load failed\..*?(?=Unsupported|Trying|Can only|$)", "", reason)
    reason = re.sub(r"Check the documentation of torch\.load.*", "", reason).strip()
    for pattern in _REFUSED:
        refused = pattern.search(reason)
        if refused:
            return (f"{path} cannot be read as a checkpoint: it pickles {refused[1]}, which safe (weights-only) "
                    "loading refuses to run; occkit does not unpickle code. If you trust the file, re-save its state "
                    "dict as plain tensors and use that")  # fmt: skip
    if "storage has wrong byte size" in reason:  # torch's message leaves its printf placeholders unfilled
        reason = "a tensor's data is not the size its pickle declares (storage has wrong byte size)"
    return f"{path} is not a readable checkpoint: {type(error).__name__}: {reason[:200] or 'no reason given'}"


def _check_tensors(payload: Any, path: Path) -> None:
    """Refuse a payload holding a tensor occkit cannot use as saved weights (see :func:`load_torch_file`).

    The walk is iterative and visits every object once: a pickle may nest containers deeply or share them."""
    seen: set[int] = set()
    pending: list[tuple[Any, str]] = [(payload, "")]
    while pending:
        value, where = pending.pop()
        if id(value) in seen:
            continue
        seen.add(id(value))
        if isinstance(value, Tensor):
            problem = _tensor_problem(value)
            if problem:
                raise ValueError(f"{path}: {where or 'the file'} is {problem}; not saved weights occkit reads")
        elif isinstance(value, (Mapping, list, tuple)):
            items = value.items() if isinstance(value, Mapping) else enumerate(value)
            # Names for messages, to a few levels (the keys of a state dict); deeper ones keep their parent's.
            pending.extend((item, f"{where}.{key}".lstrip(".") if where.count(".") < 4 else where)
                           for key, item in items)  # fmt: skip


def _tensor_problem(tensor: Tensor) -> str | None:
    if tensor.layout != torch.strided:
        return f"a {str(tensor.layout).removeprefix('torch.')} tensor, not a dense one"
    if tensor.is_meta:
        return "a meta tensor, without data"
    needed, stored = tensor.numel() * tensor.element_size(), tensor.untyped_storage().nbytes()
    if needed > stored:
        return (f"a {tuple(tensor.shape)} view of {format_bytes(needed)} over {format_bytes(stored)} of saved data "
                "(an expanded tensor)")  # fmt: skip
    return None


def check_finite(state: Mapping[str, Tensor], path: str | Path, what: str = "weights") -> None:
    """Refuse weights holding NaN or infinite values: such a model predicts nothing and scores an mIoU of 0 without
    any error, so a diverged run or a broken export is named here, with its first keys and how many values.

    Raises:
        ValueError: naming ``path``, the count of tensors that are not finite and the first keys.
    """
    bad = [key for key, tensor in state.items()
           if tensor.is_floating_point() or tensor.is_complex()
           if not bool(torch.isfinite(tensor).all())]  # fmt: skip
    if bad:
        shown = ", ".join(f"{key} ({int((~torch.isfinite(state[key])).sum())} of {state[key].numel()} values)"
                          for key in bad[:3])  # fmt: skip
        raise ValueError(f"{path}: {len(bad)} of {len(state)} tensors of its {what} hold NaN or infinite values: "
                         f"{shown}{', ...' if len(bad) > 3 else ''}; a model with them predicts nothing (was the run "
                         "diverging when they were saved?)")  # fmt: skip


def read_safetensors(path: str | Path) -> tuple[dict[str, Tensor], dict[str, str]]:
    """Tensors and metadata of a ``.safetensors`` file.

    Raises:
        ValueError: not a readable safetensors file (the message names it).
    """
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = dict(handle.metadata() or {})
            state = {key: handle.get_tensor(key) for key in handle.keys()}  # noqa: SIM118 (safe_open has no __iter__)
    except (SafetensorError, OSError, ValueError) as error:
        raise ValueError(f"{path} is not a readable .safetensors file: {' '.join(str(error).split())}") from error
    return state, metadata


# ----------------------------------------------------------------------------------------------------- checkpoints
@dataclass
class ReferenceCheckpoint:
    """The tensors of a checkpoint file and what else it held."""

    path: Path
    state: dict[str, Tensor]
    """The model's state dict, ``module.`` prefixes stripped."""
    ignored: dict[str, str]
    """Top-level entries besides the weights (mmcv's ``meta``, ``optimizer``, ...) -> what they are."""
    metadata: dict[str, str]
    """A ``.safetensors`` file's metadata (empty otherwise)."""
    occkit: bool
    """An occkit checkpoint or converted weights (occkit's names)."""
    architecture: str | None = None
    """The architecture an occkit file says its weights are of (None: not said)."""


#: What the top-level entries of mmcv / occkit checkpoints besides the weights hold.
_TOP_LEVEL = {
    "meta": "mmcv run metadata: config text, versions, epoch",
    "optimizer": "optimizer state, for training only",
    "updates": "EMA update count, for training only",
    "epoch": "epoch counter",
    "iter": "iteration counter",
    "lr_scheduler": "scheduler state, for training only",
    "scaler": "mixed-precision loss scale, for training only",
}


def strip_wrappers(state: Mapping[str, Any]) -> dict[str, Any]:
    """Keys without DistributedDataParallel's ``module.`` prefix."""
    return {key.removeprefix("module."): value for key, value in state.items()}


def _tensor_dict(state: Any, path: Path, what: str) -> dict[str, Tensor]:
    if not isinstance(state, Mapping) or not state:
        raise ValueError(f"{path}: {what} is not a non-empty dict of tensors")
    wrong = [key for key, value in state.items() if not isinstance(value, Tensor)]
    if wrong:
        raise ValueError(f"{path}: {what} holds non-tensor entries ({', '.join(map(str, wrong[:4]))})")
    return strip_wrappers(state)


def read_checkpoint(path: str | Path) -> ReferenceCheckpoint:
    """The state dict of a checkpoint file, read without unpickling code.

    Reads ``.safetensors`` files, occkit checkpoints (their EMA weights when they have them), mmcv checkpoints
    (``{'meta', 'state_dict', 'optimizer'}``, the EMA hook's ``epoch_N_ema.pth`` too) and bare state dicts. Weights
    that are NaN or infinite are refused (:func:`~occkit.weight_files.check_finite`): converted or loaded, they
    would score an mIoU of 0 without any error.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file cannot be read safely, holds no state dict, or weights that are not finite (the message
            names the file and why).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    checkpoint = _read_state(path)
    check_finite(checkpoint.state, path)
    return checkpoint


def _read_state(path: Path) -> ReferenceCheckpoint:
    """:func:`read_checkpoint` without its checks of the values."""
    if path.suffix == ".safetensors":
        state, metadata = read_safetensors(path)
        return ReferenceCheckpoint(path, state, {}, metadata, occkit=metadata.get("format") == WEIGHTS_FORMAT,
                                   architecture=metadata.get("architecture"))  # fmt: skip
    payload = load_torch_file(path)
    if isinstance(payload, Mapping) and str(payload.get("format", "")).startswith(_CHECKPOINT_FORMAT_PREFIX):
        key = "ema" if payload.get("ema") is not None else "model"
        ignored = {k: "occkit run state" for k in payload if k != key}
        return ReferenceCheckpoint(path, _tensor_dict(payload[key], path, f"its '{key}'"), ignored, {}, occkit=True,
                                   architecture=payload.get("architecture"))  # fmt: skip
    if isinstance(payload, Mapping):
        for key in ("state_dict", "model"):
            if isinstance(payload.get(key), Mapping):
                ignored = {k: _TOP_LEVEL.get(k, "not model weights") for k in payload if k != key}
                state = _tensor_dict(payload[key], path, f"its '{key}'")
                return ReferenceCheckpoint(path, state, ignored, {}, occkit=False)
        if payload and all(isinstance(v, Tensor) for v in payload.values()):
            return ReferenceCheckpoint(path, _tensor_dict(payload, path, "the file"), {}, {}, occkit=False)
        top = ", ".join(map(str, list(payload)[:6]))
        raise ValueError(f"{path} holds no state dict (top-level keys: {top}; expected 'state_dict' or tensors)")
    raise ValueError(f"{path} holds a {type(payload).__name__}, not a checkpoint dict")
