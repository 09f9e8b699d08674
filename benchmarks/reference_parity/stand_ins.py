"""The thinnest stand-ins for the OpenMMLab packages that the reference code imports at module level.

The reference repositories (Yzichen/FlashOCC, AlphaPlusTT/DAOcc) import mmcv 1.x, mmdet 2.x and mmdet3d 1.x, whose
compiled ops do not build here. The harness runs only reference functions that need none of them (image and BEV
augmentation bookkeeping), so each imported name is a placeholder: a registry whose ``register_module()`` returns the
class unchanged, and classes that fail loudly if anything ever instantiates them. :func:`installed` puts them in
``sys.modules`` for the duration of an import and removes them afterwards.
"""

from __future__ import annotations

import contextlib
import sys
import types
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from openmmlab import placeholder  # noqa: E402 - beside this module


class Registry:
    """mmcv's ``Registry`` reduced to its decorator: the class is kept unchanged."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.modules: dict[str, type] = {}

    def register_module(self, *args, **kwargs):
        def register(cls: type) -> type:
            self.modules[cls.__name__] = cls
            return cls

        return register


def _base_module() -> type:
    """mmcv's ``BaseModule``: an ``nn.Module`` (its weight initialisation from configs is not used here)."""
    from torch import nn

    return type("BaseModule", (nn.Module,), {})


def _force_fp32(*args, **kwargs):
    """mmcv's ``force_fp32`` decorator factory: the function unchanged (the harness runs in fp32)."""
    return lambda function: function


#: Names whose stand-in is not a placeholder.
_SPECIAL = {"BaseModule": _base_module, "force_fp32": lambda: _force_fp32}

#: module -> names it must provide (placeholders unless a registry or in _SPECIAL). FlashOcc's plugin package is
#: included so that a module of it imports with its relative imports (``...ops``: its CUDA ops) resolved to stand-ins.
_MODULES: dict[str, tuple[str, ...]] = {
    "mmcv": ("is_tuple_of",),
    "mmcv.utils": ("build_from_cfg",),
    "mmcv.runner": ("BaseModule", "force_fp32"),
    "mmdet3d.models": (),
    "mmdet3d.models.builder": ("NECKS",),
    "projects": (),
    "projects.mmdet3d_plugin": (),
    "projects.mmdet3d_plugin.ops": ("bev_pool_v2",),
    "projects.mmdet3d_plugin.models": (),
    "projects.mmdet3d_plugin.models.necks": (),
    "projects.mmdet3d_plugin.models.model_utils": ("DepthNet",),
    "mmdet": (),
    "mmdet.datasets": (),
    "mmdet.datasets.pipelines": ("LoadAnnotations", "LoadImageFromFile"),
    "mmdet.datasets.builder": ("PIPELINES",),
    "mmdet3d": (),
    "mmdet3d.core": ("VoxelGenerator",),
    "mmdet3d.core.points": ("BasePoints", "get_points_type"),
    "mmdet3d.core.bbox": ("LiDARInstance3DBoxes", "CameraInstance3DBoxes", "DepthInstance3DBoxes", "box_np_ops"),
    "mmdet3d.datasets": (),
    "mmdet3d.datasets.builder": ("PIPELINES", "OBJECTSAMPLERS"),
    "mmdet3d.datasets.pipelines": (),
    "mmdet3d.datasets.pipelines.utils": ("noise_per_object_v3_",),
    "pyquaternion": ("Quaternion",),
}


@contextlib.contextmanager
def installed() -> Iterator[dict[str, types.ModuleType]]:
    """The stand-in modules in ``sys.modules`` (a module already imported is kept), removed on exit."""
    added: dict[str, types.ModuleType] = {}
    for name, attributes in _MODULES.items():
        if name in sys.modules:
            continue
        module = types.ModuleType(name)
        module.__path__ = []  # a package, so that submodules import
        for attribute in attributes:
            if attribute in _SPECIAL:
                value = _SPECIAL[attribute]()
            else:
                value = Registry(attribute) if attribute.isupper() else placeholder(attribute)
            setattr(module, attribute, value)
        sys.modules[name] = added[name] = module
    try:
        yield added
    finally:
        for name in added:
            sys.modules.pop(name, None)
