"""Reading weight files without running their code: torch files loaded weights-only, and ``.safetensors``.

Checkpoints of the reference toolkits (mmcv, mmdet3d) pickle a ``meta`` dict beside the weights, which may hold numpy
scalars and arrays (an evaluation hook's scores); those reconstructors are allowed beside torch's weights-only set,
since they rebuild plain numbers and arrays and nothing callable. Anything else a file would unpickle is refused with
a message naming the file and the refused global. The pretrained backbones (:mod:`occkit.models.pretrained`) and the
checkpoint converter (:mod:`occkit.convert`) read through here.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

__all__ = ["load_torch_file", "read_safetensors"]


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


def load_torch_file(path: str | Path) -> Any:
    """The object a torch file holds, loaded weights-only on the CPU (numpy metadata allowed).

    Raises:
        ValueError: the file cannot be read safely or at all (the message names the file and why).
    """
    try:
        with torch.serialization.safe_globals(_numpy_globals()):
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises UnpicklingError, RuntimeError, EOFError, ... for unreadable files
        text = " ".join(str(error).split())
        refused = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
        if refused:
            why = (f"it pickles {refused[1]}, which safe (weights-only) loading refuses to run; occkit does not "
                   "unpickle code. If you trust the file, re-save its state dict as plain tensors and use that")
        else:
            why = f"{type(error).__name__}: {text[:300]}"
        raise ValueError(f"{path} cannot be read as a checkpoint: {why}") from error


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
