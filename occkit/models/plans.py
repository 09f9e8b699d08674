"""A model's plan (:mod:`occkit.models.base`) as named tensors: what the deployed network keeps as buffers and a CUDA
graph copies into its captured memory."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from torch import Tensor

__all__ = ["plan_tensors", "plan_with_tensors"]


def plan_tensors(plan: Any, prefix: str = "") -> dict[str, Tensor]:
    """The tensors of a plan (a dataclass, possibly nested, or None), by dotted path."""
    if plan is None:
        return {}
    if isinstance(plan, Tensor):
        return {prefix: plan}
    if not dataclasses.is_dataclass(plan):
        return {}
    found = {}
    for field in dataclasses.fields(plan):
        found.update(plan_tensors(getattr(plan, field.name), f"{prefix}{field.name}."))
    return {path.rstrip("."): tensor for path, tensor in found.items()}


def plan_with_tensors(plan: Any, tensors: Mapping[str, Tensor | None], prefix: str = "") -> Any:
    """``plan`` with the values at the paths of ``tensors`` (as :func:`plan_tensors` gives them) replaced: by tensors
    to fill a plan, or by None to keep only its structure and sizes."""
    path = prefix.rstrip(".")
    if path in tensors:
        return tensors[path]
    if plan is None or not dataclasses.is_dataclass(plan):
        return plan
    changes = {f.name: plan_with_tensors(getattr(plan, f.name), tensors, f"{prefix}{f.name}.")
               for f in dataclasses.fields(plan)}  # fmt: skip
    return dataclasses.replace(plan, **changes)
