"""Input checks shared by the geometry functions."""

from __future__ import annotations

from torch import Tensor


def check_shape(x: Tensor, tail: tuple[int, ...], name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``x`` has shape ``(..., *tail)``."""
    if x.ndim < len(tail) or tuple(x.shape[x.ndim - len(tail) :]) != tail:
        expected = ", ".join(["..."] + [str(n) for n in tail])
        raise ValueError(f"{name} must have shape ({expected}), got {tuple(x.shape)}")
