"""What a reference's conversion table is made of: the family its keys belong to, rename rules and drops.

Each rule full-matches a reference key and names the occkit key that plays its part; its ``layout`` says whether the
tensor is also re-laid. Layouts that differ, and why the tensors are changed rather than only renamed:

* **BEV axes.** occkit keeps every BEV map as ``(B, C, X, Y)``. BEVDet/FlashOcc run their BEV encoder and occupancy
  head on ``(B, C, Y, X)``, and DAOcc's occupancy head swaps its ``(X, Y)`` input to ``(Y, X)`` before its
  ``final_conv``. Convolving the transposed map with the transposed kernel gives the transposed result, so the
  kernels of exactly those convolutions are transposed (``weight.transpose(-1, -2)``, a no-op for 1 x 1 kernels);
  all else in those modules (BatchNorm, biases, linear layers) is unchanged.
* **Sparse convolutions.** DAOcc's ``SparseEncoder`` uses the spconv 1.x bundled in its ``mmdet3d/ops/spconv``
  (its docs/install.md installs no spconv package), whose weights are ``(kx, ky, kz, in, out)``; spconv 2.x, which
  occkit uses, stores ``(out, kx, ky, kz, in)``. The kernel axes are in the same order on both sides: BEVFusion's
  voxelizer writes ``(x, y, z)`` coordinates (not mmdet3d's usual ``(z, y, x)``) for its ``[1440, 1440, 41]`` sparse
  shape, as occkit does, so the permutation is ``(4, 0, 1, 2, 3)`` and nothing else. A checkpoint re-saved from
  spconv 2.x already has occkit's layout; the layout is read off the shapes, once per checkpoint, and reported.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Source:
    """A family of checkpoints, recognised by the prefixes of its keys."""

    kind: str
    """``flashocc``, ``daocc`` or ``occkit``."""
    description: str
    """What such a checkpoint is, for messages."""
    architecture: str | None
    """The occkit architecture its weights belong to (None: any, the names are occkit's own)."""
    prefixes: tuple[str, ...]
    """Key prefixes only this family uses."""
    default_entry: str | None
    """The zoo entry a conversion targets when none is named."""


#: Layout changes (see the module docstring). ``same``: renamed only.
SAME, BEV_YX, SPARSE = "same", "bev_yx", "sparse"

#: BatchNorm's tensors, one regex group.
_BN = r"(weight|bias|running_mean|running_var|num_batches_tracked)"

Target = Callable[[re.Match], "str | None"]


@dataclass(frozen=True)
class Rule:
    """A reference key pattern (full match) and its occkit name; ``layout`` says how the tensor is re-laid."""

    pattern: re.Pattern
    target: Target
    layout: str = SAME


@dataclass(frozen=True)
class Drop:
    """Reference keys occkit does not keep, and why."""

    pattern: re.Pattern
    reason: str


def _rule(pattern: str, target: str | Target, layout: str = SAME) -> Rule:
    """``target``: a ``re`` template (``\\1``) or a function of the match returning the name (None: no mapping)."""
    expand = (lambda m: m.expand(target)) if isinstance(target, str) else target
    return Rule(re.compile(pattern), expand, layout)


def _drop(pattern: str, reason: str) -> Drop:
    return Drop(re.compile(pattern), reason)
