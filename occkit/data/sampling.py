"""Class-balanced grouping and sampling (CBGS), as mmdetection3d defines it.

CBGS (Zhu et al., "Class-balanced Grouping and Sampling for Point Cloud 3D Object Detection", 2019,
arXiv:1908.09492) resamples the training split so that rare detection classes are seen about as often as common
ones. occkit follows mmdetection3d's ``CBGSDataset`` (``mmdet3d/datasets/dataset_wrappers.py``), which DAOcc and
FlashOcc train with, formula for formula:

* for each class ``c`` of ``K`` classes, ``S_c`` is the list of the samples that hold a box of ``c``, in sample
  order (a sample with boxes of three classes is in three lists; which boxes count is the dataset's business, see
  :meth:`occkit.data.dataset.OccupancyDataset.sample_classes`);
* ``D = sum_c |S_c|`` and ``ratio_c = (1 / K) / (|S_c| / D)``;
* ``int(|S_c| * ratio_c)`` samples are drawn from ``S_c`` with replacement, about ``D / K`` per class;
* the draws are concatenated in class order. An epoch runs over this list (``EpochSampler``'s ``population``).

The count is the same float expression as mmdetection3d's, so it rounds the same way: ``int(5 * ((1 / 3) / (5 /
12)))`` is 3, not 4. The draws come from ``np.random.RandomState(seed).choice``, one call per class in class order:
the legacy generator that mmdetection3d's global ``np.random.choice`` is, so the same seed given to
``np.random.seed`` before mmdetection3d builds its wrapper gives the same list.

One difference: mmdetection3d divides by zero where a class has no sample (``|S_c| = 0``); occkit leaves that class
out (no draws from it, ``K`` still counts it, as the reference's ``1 / len(CLASSES)`` does).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

import numpy as np

__all__ = ["class_samples", "cbgs_indices"]


def class_samples(sample_classes: Sequence[Collection[str]], classes: Sequence[str]) -> list[list[int]]:
    """``S_c`` of the module doc: for each of ``classes``, in order, the indices of the samples that hold it.

    Args:
        sample_classes: per sample, the classes of its boxes (any collection; repeats count once, names outside
            ``classes`` are ignored, as mmdetection3d's ``get_cat_ids`` ignores them).
        classes: the classes to balance, e.g. :data:`occkit.classes.DETECTION_CLASSES`.

    Returns:
        ``len(classes)`` lists of sample indices, each rising.
    """
    return [[i for i, present in enumerate(sample_classes) if name in present] for name in classes]


def cbgs_indices(sample_classes: Sequence[Collection[str]], classes: Sequence[str], seed: int) -> list[int]:
    """The CBGS list of sample indices (the module doc's definition): what one epoch runs over.

    Args:
        sample_classes: per sample, the classes of its boxes, e.g.
            :meth:`~occkit.data.dataset.OccupancyDataset.sample_classes`.
        classes: the ``K`` classes to balance, in the order of the draws (mmdetection3d's ``CLASSES``).
        seed: seed of the draws; the same seed gives the same list.

    Returns:
        About ``D`` indices into ``sample_classes`` (``D``: the sum over classes of the samples holding each; a
        little less after rounding down), with repeats: class ``c``'s draws, then class ``c + 1``'s.

    Raises:
        ValueError: ``classes`` is empty or repeats a class, or no sample holds any of them (nothing to balance).
    """
    if not classes:
        raise ValueError("CBGS needs at least one class to balance")
    repeated = sorted({name for name in classes if list(classes).count(name) > 1})
    if repeated:
        raise ValueError(f"CBGS classes must be distinct; {', '.join(map(repr, repeated))} repeated")
    per_class = class_samples(sample_classes, classes)
    duplicated = sum(len(samples) for samples in per_class)
    if duplicated == 0:
        raise ValueError(
            f"no sample of {len(sample_classes)} holds a box of the classes {', '.join(classes)}: CBGS has nothing "
            "to balance"
        )
    rng = np.random.RandomState(seed)
    fraction = 1.0 / len(classes)
    indices: list[int] = []
    for samples in per_class:
        if not samples:
            continue  # mmdetection3d would divide by zero; no draws, and K still counts the class
        # mmdetection3d's expressions, evaluated in the same order: the distribution, the ratio, then the count.
        ratio = fraction / (len(samples) / duplicated)
        indices += rng.choice(samples, int(len(samples) * ratio)).tolist()
    return indices
