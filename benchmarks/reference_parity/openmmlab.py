"""Stand-ins for running the reference model code on the pure-Python parts of mmcv 1.x and mmdet 2.x.

The model code of Yzichen/FlashOCC imports mmcv 1.x, mmdet 2.x and mmdet3d 1.0. mmcv and mmdet install without their
compiled ops (``MMCV_WITH_OPS=0``, see docs/reproducing.md) and are used as they are: mmdet's ``ResNet``, mmcv's
``ConvModule``, the registries and the loss utilities are the real ones. What cannot be installed is replaced here,
by the thinnest thing the models need:

* ``mmcv.ops`` (compiled): every name is a placeholder class that fails loudly when used; mmdet imports a few of them
  at module level (NMS, RoI ops) for models the harness never builds.
* ``mmdet3d`` 1.0 (its ops need CUDA to build): ``mmdet3d.models`` with its registries, which in mmdet3d 1.0 hand
  every type they do not hold to mmdet's, so they are mmdet's ``MODELS`` here; its builders; and ``CenterPoint``,
  the base of BEVDet's detectors, reduced to what an image-only detector without ``pts_bbox_head`` uses from
  ``MVXTwoStageDetector.__init__``: building ``img_backbone`` and ``img_neck`` and ``with_img_neck``.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import sys
import types
from collections.abc import Iterator


def placeholder(name: str) -> type:
    """A class the reference imports but the harness must never use."""

    def refuse(*args, **kwargs):
        raise RuntimeError(f"{name} is a stand-in of the parity harness: the reference code used it after all")

    return type(name, (), {"__init__": refuse, "__call__": refuse, "apply": staticmethod(refuse)})


class _PlaceholderPackage(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports ``prefix`` and its submodules as modules whose every attribute is a :func:`placeholder`."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix

    def find_spec(self, fullname, path, target=None):
        if fullname == self.prefix or fullname.startswith(self.prefix + "."):
            return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
        return None

    def create_module(self, spec):
        module = types.ModuleType(spec.name)
        module.__path__ = []
        module.__getattr__ = lambda attribute: self._attribute(spec.name, attribute)
        return module

    @staticmethod
    def _attribute(module: str, attribute: str) -> type:
        if attribute.startswith("__"):  # what Python's own machinery asks of a module, e.g. __file__
            raise AttributeError(attribute)
        return placeholder(f"{module}.{attribute}")

    def exec_module(self, module) -> None:
        pass


def _mmdet3d_models() -> types.ModuleType:
    """``mmdet3d.models`` (also its ``builder``) on mmdet's registry."""
    from mmdet.models import builder as mmdet_builder
    from torch import nn

    registry = mmdet_builder.MODELS
    module = types.ModuleType("mmdet3d.models")
    module.__path__ = []
    for name in ("MODELS", "DETECTORS", "BACKBONES", "NECKS", "HEADS", "LOSSES", "FUSION_LAYERS", "MIDDLE_ENCODERS",
                 "VOXEL_ENCODERS", "SEGMENTORS", "ROI_EXTRACTORS", "SHARED_HEADS"):  # fmt: skip
        setattr(module, name, registry)
    for name in ("build_backbone", "build_neck", "build_head", "build_loss", "build_detector", "build_model"):
        setattr(module, name, lambda cfg, *args, **kwargs: registry.build(cfg))
    module.builder = module

    class CenterPoint(nn.Module):
        """mmdet3d's ``MVXTwoStageDetector`` as an image-only detector uses it (its point branch must be unset)."""

        def __init__(self, img_backbone=None, img_neck=None, pts_bbox_head=None, train_cfg=None, test_cfg=None,
                     pretrained=None, init_cfg=None, **point_branch):  # fmt: skip
            super().__init__()
            given = sorted(key for key, value in point_branch.items() if value is not None)
            if pts_bbox_head is not None or given:
                raise RuntimeError(f"the CenterPoint stand-in builds no point branch, got {given or 'pts_bbox_head'}")
            self.img_backbone = registry.build(img_backbone) if img_backbone else None
            self.img_neck = registry.build(img_neck) if img_neck else None
            self.train_cfg, self.test_cfg = train_cfg, test_cfg

        @property
        def with_img_neck(self) -> bool:
            return self.img_neck is not None

    module.CenterPoint = CenterPoint
    return module


@contextlib.contextmanager
def installed(extra: dict[str, types.ModuleType] | None = None) -> Iterator[None]:
    """``mmcv.ops``, ``mmdet3d`` and ``extra`` (module name -> module) importable; all removed on exit, with every
    module imported meanwhile from under them."""
    finder = _PlaceholderPackage("mmcv.ops")
    sys.meta_path.insert(0, finder)
    before = set(sys.modules)
    models = _mmdet3d_models()
    modules = {"mmdet3d": types.ModuleType("mmdet3d"), "mmdet3d.models": models, "mmdet3d.models.builder": models,
               "mmdet3d.core": types.ModuleType("mmdet3d.core"), **(extra or {})}  # fmt: skip
    modules["mmdet3d"].__path__ = []
    modules["mmdet3d.core"].bbox3d2result = placeholder("mmdet3d.core.bbox3d2result")
    sys.modules.update(modules)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
        for name in set(sys.modules) - before:
            if name.startswith(("mmcv.ops", "mmdet3d", "projects")) or name in modules:
                sys.modules.pop(name, None)
