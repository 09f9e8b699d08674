"""Stand-ins for running the reference model code on the pure-Python parts of mmcv 1.x and mmdet 2.x.

The model code of Yzichen/FlashOCC imports mmcv 1.x, mmdet 2.x and mmdet3d 1.0. mmcv and mmdet install without their
compiled ops (``MMCV_WITH_OPS=0``, see docs/reproducing.md) and are used as they are: mmdet's ``ResNet``, mmcv's
``ConvModule``, the registries and the loss utilities are the real ones. What cannot be installed is replaced here,
by the thinnest thing the models need:

* ``mmcv.ops`` (compiled): every name is a :func:`placeholder` that fails loudly when used; mmdet imports a few of them
  at module level (NMS, RoI ops) for models the harness never builds. :func:`stand_ins` answers such imports, and
  the DAOcc harness's compiled ops (:mod:`daocc_ops`) through it too.
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
    """A stand-in for the function or class ``name`` the reference imports but the harness must not run: it imports
    (and can be subclassed), and raises as soon as anything calls or instantiates it, or ``apply``s it as an autograd
    function, so that nothing the harness did not define runs unnoticed."""

    def refuse(*args, **kwargs):
        raise RuntimeError(f"{name} is a stand-in of the parity harness (no PyTorch definition): the reference code "
                           "ran it")

    module, _, short = name.rpartition(".")
    return type(short, (), {"__init__": refuse, "apply": classmethod(refuse), "__module__": module})


class StandInFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Answers, before the ordinary finders, the imports of the modules in ``defined`` (module -> the names it is given
    a definition of) and of the ``packages`` replaced whole, submodules included; any other name of theirs is a
    :func:`placeholder`."""

    def __init__(self, defined: dict[str, dict[str, object]], packages: tuple[str, ...]) -> None:
        self.defined, self.packages = defined, packages

    def _claims(self, name: str) -> bool:
        return name in self.defined or any(name == root or name.startswith(root + ".") for root in self.packages)

    def find_spec(self, name, path=None, target=None):
        return importlib.machinery.ModuleSpec(name, self, is_package=True) if self._claims(name) else None

    def create_module(self, spec):
        module = types.ModuleType(spec.name)
        module.__path__ = []  # a package, so that ``from mmcv.ops.nms import ...`` resolves here too
        module.__dict__.update(self.defined.get(spec.name, {}))

        def missing(attribute: str):
            if attribute.startswith("__"):  # what Python's own machinery asks of a module, e.g. __file__
                raise AttributeError(attribute)
            return placeholder(f"{spec.name}.{attribute}")

        module.__getattr__ = missing
        return module

    def exec_module(self, module) -> None:
        """Nothing to run: :meth:`create_module` made the module whole."""


@contextlib.contextmanager
def stand_ins(defined: dict[str, dict[str, object]], packages: tuple[str, ...] = ("mmcv.ops",)) -> Iterator[None]:
    """A :class:`StandInFinder` answers imports while the context lasts; the modules it made are removed on exit."""
    finder = StandInFinder(defined, packages)
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
        for name in [name for name, module in sys.modules.items() if getattr(module, "__loader__", None) is finder]:
            del sys.modules[name]


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
    """``mmcv.ops`` placeholders, the ``mmdet3d`` stand-ins and ``extra`` (module name -> module) importable; all
    removed on exit, with every module imported meanwhile from under them."""
    with stand_ins({}):
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
            for name in set(sys.modules) - before:
                if name.startswith(("mmdet3d", "projects")) or name in modules:
                    sys.modules.pop(name, None)
