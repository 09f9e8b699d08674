"""Pretrained image backbones: the ``pretrained`` setting of :class:`~occkit.models.image_encoder.ImageEncoderConfig`.

A setting is one of

* ``torchvision:WEIGHTS``, e.g. ``torchvision:IMAGENET1K_V1``: the member ``WEIGHTS`` of torchvision's
  ``ResNet{depth}_Weights`` for the configured depth, fetched by torchvision itself into torch's hub cache
  (``$TORCH_HOME/hub/checkpoints``), so a machine with a network downloads it once and later runs read the cache;
* an ``https://`` address of a checkpoint, e.g. mmdetection3d's nuImages detectors (what mmcv's ``Pretrained``
  initialisation takes), downloaded with torch's hub into the same cache;
* ``timm:NAME``, e.g. ``timm:resnet50.a1_in1k``: the weights of ``timm.create_model(NAME, pretrained=True)``, fetched
  by timm into the Hugging Face cache;
* a local file: a torchvision / timm ResNet state dict (``.pth``, ``.pt``, ``.bin`` or ``.safetensors``), or an
  mmdetection / mmdetection3d checkpoint whose backbone keys (under ``backbone.``, ``img_backbone.`` or
  ``encoders.camera.backbone.``) are picked out: mmdet's "pytorch"-style ResNet names its parameters as torchvision
  does, so a nuImages detector's backbone loads as it is;
* an occkit checkpoint (``occkit train``'s ``step-*.pt``, or its ``.safetensors`` weights): the backbone of its image
  encoder, under ``image_encoder.backbone.``, so that one trained model's backbone starts another of any architecture
  with the same ResNet.

Building a model never reads weights (a model built for counting parameters or for a test needs no file);
:func:`initialise` loads them into every backbone of a built model, which ``occkit train`` does before the first step
of a fresh run. Without a network, a named source that is not cached fails with one line naming the file, where to
put it and the setting that takes a local copy instead.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from occkit.config import ConfigError
from occkit.weight_files import check_finite, load_torch_file, read_safetensors

__all__ = ["PretrainedUnavailable", "parse", "needed_file", "backbone_state", "initialise", "load_state_dict_file",
           "SETTING", "backbone_settings", "ensure_available"]

#: The experiment key that holds a backbone's weights (every architecture names its image encoder ``image``).
SETTING = "model.image.pretrained"

#: Key prefixes under which detector checkpoints keep their image backbone (mmdet, BEVDet / FlashOcc, BEVFusion /
#: DAOcc, occkit), tried in this order after an optional DistributedDataParallel ``module.``.
_BACKBONE_PREFIXES = ("backbone.", "img_backbone.", "encoders.camera.backbone.", "image_encoder.backbone.")


class PretrainedUnavailable(OSError):
    """A named source is neither cached nor downloadable (no network); the message says what to fetch where."""


@dataclass(frozen=True)
class Source:
    """A parsed ``pretrained`` setting."""

    kind: str
    """``torchvision``, ``url``, ``timm`` or ``file``."""
    name: str
    """The weights member, the timm model name, or the path."""


def parse(setting: str) -> Source:
    """The source a ``pretrained`` string names (``torchvision:``, ``timm:`` or a path)."""
    if setting.startswith(("https://", "http://")):
        return Source("url", setting)
    kind, _, name = setting.partition(":")
    if kind in ("torchvision", "timm") and name:
        return Source(kind, name)
    return Source("file", setting)


def _torchvision_weights(name: str, depth: int):
    import torchvision

    enum = getattr(torchvision.models, f"ResNet{depth}_Weights", None)
    if enum is None or not hasattr(enum, name):
        members = ", ".join(enum.__members__) if enum is not None else "none"
        raise ConfigError(f"{SETTING}: torchvision has no ResNet{depth}_Weights.{name} (members: {members})")
    return getattr(enum, name)


def needed_file(setting: str, depth: int) -> str:
    """What a user must have for ``setting``: the cached file name of a torchvision source (e.g.
    ``resnet50-0676ba61.pth``), the timm model of a timm source, or the local path."""
    source = parse(setting)
    if source.kind == "torchvision":
        return Path(_torchvision_weights(source.name, depth).url).name
    if source.kind == "url":
        return Path(source.name).name
    if source.kind == "timm":
        return f"timm model {source.name}"
    return source.name


def load_state_dict_file(path: str | Path) -> dict[str, Tensor]:
    """Tensors of a local ``.safetensors`` or torch file, loaded without unpickling code
    (:mod:`occkit.weight_files`); an mmcv checkpoint's ``state_dict`` (or an occkit checkpoint's ``model``) is taken
    out of it. Weights that are not finite are refused (a backbone of NaNs trains nothing, silently)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weights file {path} does not exist")
    state = read_safetensors(path)[0] if path.suffix == ".safetensors" else load_torch_file(path)
    if isinstance(state, dict):
        for key in ("state_dict", "model"):
            if isinstance(state.get(key), Mapping):
                state = state[key]
                break
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(f"{path} holds no state dict of tensors")
    check_finite(state, path)
    return dict(state)


def _backbone_keys(state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """torchvision-named ResNet tensors of a state dict: its backbone's under a detector's prefix, else all of it;
    the classifier (``fc.``) left out."""
    state = {k.removeprefix("module."): v for k, v in state.items()}
    for prefix in _BACKBONE_PREFIXES:
        picked = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        if picked:
            state = picked
            break
    return {k: v for k, v in state.items() if not k.startswith("fc.")}


def _hub_file(url: str, setting: str) -> Path:
    """The cached copy of ``url`` in torch's hub cache, downloaded first if missing."""
    cache = Path(torch.hub.get_dir()) / "checkpoints"
    path = cache / Path(url).name
    if path.is_file():
        return path
    try:
        cache.mkdir(parents=True, exist_ok=True)
        torch.hub.download_url_to_file(url, str(path), progress=True)  # writes a temporary file, then renames it
    except Exception as error:  # no network: URLError, socket errors, HTTP errors
        named = "" if setting == url else f" = {setting}"
        raise PretrainedUnavailable(
            f"{SETTING}{named} needs {path.name} from {url}: it is not in {cache} and cannot be downloaded "
            f"({type(error).__name__}); put the file there, or set {SETTING}=PATH to a local copy"
        ) from None
    return path


def _download_or_cached(source: Source, depth: int) -> dict[str, Tensor]:
    if source.kind in ("torchvision", "url"):
        url = _torchvision_weights(source.name, depth).url if source.kind == "torchvision" else source.name
        setting = f"torchvision:{source.name}" if source.kind == "torchvision" else source.name
        return load_state_dict_file(_hub_file(url, setting))
    import timm

    try:
        return timm.create_model(source.name, pretrained=True).state_dict()
    except RuntimeError as error:  # an unknown model name
        raise ConfigError(f"{SETTING}: timm cannot make {source.name!r}: {error}") from None
    except Exception as error:  # no network and not in the Hugging Face cache
        raise PretrainedUnavailable(
            f"{SETTING} = timm:{source.name} is not in the Hugging Face cache and could not be downloaded "
            f"({type(error).__name__}): fetch it where timm looks (HF_HOME), or set {SETTING}=PATH to a local copy"
        ) from None


def backbone_state(setting: str, depth: int) -> dict[str, Tensor]:
    """torchvision-named ResNet weights (no classifier) of a ``pretrained`` setting.

    Raises:
        PretrainedUnavailable: a named source is not cached and cannot be downloaded.
        FileNotFoundError, ValueError: a local file is missing or holds no weights.
    """
    source = parse(setting)
    state = load_state_dict_file(source.name) if source.kind == "file" else _download_or_cached(source, depth)
    return _backbone_keys(state)


def backbone_settings(config: Any) -> list[tuple[str, int]]:
    """``(pretrained, depth)`` of every image encoder with weights in a model config (found among its fields)."""
    from occkit.models.image_encoder import ImageEncoderConfig

    if isinstance(config, ImageEncoderConfig):
        return [(config.pretrained, config.depth)] if config.pretrained else []
    if not dataclasses.is_dataclass(config):
        return []
    return [found for f in dataclasses.fields(config) for found in backbone_settings(getattr(config, f.name))]


def ensure_available(config: Any) -> None:
    """Check, before any data is read, that every backbone's weights can be had: a local file exists, a named source
    is cached or downloads now (into its library's cache, where :func:`initialise` then reads it).

    Raises:
        PretrainedUnavailable: a named source is neither cached nor downloadable.
        FileNotFoundError: a local file is missing.
    """
    for setting, depth in backbone_settings(config):
        source = parse(setting)
        if source.kind == "file" and not Path(source.name).is_file():
            raise FileNotFoundError(f"{SETTING} = {setting}: no such file (a {needed_file(setting, depth)} "
                                    "state dict or checkpoint)")  # fmt: skip
        if source.kind in ("torchvision", "url"):
            _hub_file(_torchvision_weights(source.name, depth).url if source.kind == "torchvision" else source.name,
                      setting)
        elif source.kind == "timm":
            _download_or_cached(source, depth)


def initialise(model: nn.Module, whole_model_weights: bool = False) -> list[str]:
    """Load every image backbone's ``pretrained`` weights into ``model``; returns the settings loaded.

    Args:
        model: a freshly built model.
        whole_model_weights: the run loads a whole model afterwards (``train.load_from``), which brings backbone
            weights of its own.

    Raises:
        ConfigError: a backbone keeps BatchNorm statistics or stages frozen (``norm_eval`` / ``frozen_stages``) but
            has no pretrained weights, which would freeze its initial values for the whole run.
    """
    from occkit.models.image_encoder import ResNetBackbone

    loaded = []
    for backbone in (m for m in model.modules() if isinstance(m, ResNetBackbone)):
        if backbone.pretrained:
            backbone.load_torchvision_state(backbone_state(backbone.pretrained, backbone.depth), backbone.pretrained)
            loaded.append(backbone.pretrained)
        elif not whole_model_weights and (backbone.norm_eval or backbone.frozen_stages >= 0):
            frozen = "norm_eval" if backbone.norm_eval else "frozen_stages"
            raise ConfigError(
                f"model.image.{frozen} freezes a randomly initialised backbone ({SETTING} is not set): BatchNorm "
                "would normalise with its initial statistics (mean 0, variance 1) for the whole run; set "
                f"{SETTING} (e.g. torchvision:IMAGENET1K_V1 or a local file) or turn {frozen} off"
            )
    return loaded
