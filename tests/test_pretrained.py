"""Pretrained backbones: local files of every kind, named sources through their libraries' caches, offline errors,
and the refusal to freeze a randomly initialised backbone. Nothing here downloads: named sources are served from a
cache folder the tests fill, or their download is made to fail."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torchvision
from safetensors.torch import save_file

from occkit import zoo
from occkit.config import ConfigError
from occkit.models import pretrained
from occkit.models.image_encoder import ImageEncoderConfig, ResNetBackbone

TINY = {"depth": 18, "blocks": (1, 1, 1, 1), "norm_eval": False}


def _reference(blocks=(1, 1, 1, 1)) -> torchvision.models.ResNet:
    torch.manual_seed(3)
    return torchvision.models.ResNet(torchvision.models.resnet.BasicBlock, list(blocks))


def _loaded(setting: str, **cfg) -> ResNetBackbone:
    backbone = ResNetBackbone(ImageEncoderConfig(**{**TINY, **cfg}, pretrained=setting))
    pretrained.initialise(backbone)
    return backbone


def _assert_same(backbone: ResNetBackbone, reference: torchvision.models.ResNet) -> None:
    torch.testing.assert_close(backbone.stem[0].weight, reference.conv1.weight)
    torch.testing.assert_close(backbone.stem[1].running_var, reference.bn1.running_var)
    torch.testing.assert_close(backbone.stages[3][0].downsample[0].weight, reference.layer4[0].downsample[0].weight)


def test_building_never_reads_the_weights(tmp_path):
    backbone = ResNetBackbone(ImageEncoderConfig(**TINY, pretrained=str(tmp_path / "absent.pth")))
    assert backbone.pretrained.endswith("absent.pth")  # built without the file: loading is initialise's job
    model = zoo.build("daocc")  # the paper entry names a download; building it is offline and instant
    assert zoo.experiment("daocc").model.image.pretrained.startswith("https://")
    assert sum(p.numel() for p in model.parameters()) > 0


@pytest.mark.parametrize("suffix", [".pth", ".safetensors"])
def test_torchvision_state_dict_files(tmp_path, suffix):
    reference = _reference()
    path = tmp_path / f"resnet{suffix}"
    state = reference.state_dict()
    save_file(state, str(path)) if suffix == ".safetensors" else torch.save(state, path)
    _assert_same(_loaded(str(path)), reference)


def test_original_torchvision_files_without_batch_counters_load(tmp_path):
    reference = _reference()
    state = {k: v for k, v in reference.state_dict().items() if not k.endswith("num_batches_tracked")}
    torch.save(state, tmp_path / "old.pth")
    _assert_same(_loaded(str(tmp_path / "old.pth")), reference)


@pytest.mark.parametrize("prefix", ["backbone.", "img_backbone.", "encoders.camera.backbone.", "module.backbone."])
def test_detector_checkpoints_give_their_backbone(tmp_path, prefix):
    """mmdet / BEVDet / BEVFusion checkpoints: ``{"meta": ..., "state_dict": {prefix + torchvision name: ...}}`` with
    the neck and heads beside the backbone."""
    reference = _reference()
    state = {prefix + k: v for k, v in reference.state_dict().items()}
    state[prefix.replace("backbone", "neck") + "lateral_convs.0.conv.weight"] = torch.zeros(4, 4, 1, 1)
    state["roi_head.bbox_head.0.fc_cls.weight"] = torch.zeros(11, 1024)
    torch.save({"meta": {"epoch": 20, "CLASSES": ("car", "truck")}, "state_dict": state}, tmp_path / "htc.pth")
    _assert_same(_loaded(str(tmp_path / "htc.pth")), reference)


def test_an_occkit_checkpoint_starts_another_architectures_backbone(tmp_path):
    """One trained model's backbone starts another model with the same ResNet (the occkit checkpoint's ``model``,
    its image encoder's backbone picked out, the neck and heads left)."""
    torch.manual_seed(5)
    trained = zoo.build("daocc_tiny")
    torch.save({"architecture": "daocc", "step": 3, "model": trained.state_dict()}, tmp_path / "step-00000003.pt")
    cfg = zoo.experiment("flashocc_tiny").model
    model = zoo.build_from_config("flashocc", dataclasses.replace(
        cfg, image=dataclasses.replace(cfg.image, pretrained=str(tmp_path / "step-00000003.pt"))))
    assert pretrained.initialise(model) == [str(tmp_path / "step-00000003.pt")]
    for name, value in trained.image_encoder.backbone.state_dict().items():
        torch.testing.assert_close(model.image_encoder.backbone.state_dict()[name], value)


def test_timm_resnet_state_dicts_share_torchvision_names(tmp_path):
    timm = pytest.importorskip("timm")
    net = timm.create_model("resnet18", pretrained=False)
    torch.save(net.state_dict(), tmp_path / "timm.pth")
    backbone = _loaded(str(tmp_path / "timm.pth"), blocks=())
    torch.testing.assert_close(backbone.stages[2][1].conv2.weight, net.layer3[1].conv2.weight)


def test_a_backbone_keeping_fewer_stages_ignores_the_deeper_ones(tmp_path):
    reference = _reference()
    torch.save(reference.state_dict(), tmp_path / "r.pth")
    backbone = _loaded(str(tmp_path / "r.pth"), out_stages=(2,))
    assert len(backbone.stages) == 2
    torch.testing.assert_close(backbone.stages[1][0].conv1.weight, reference.layer2[0].conv1.weight)


def test_wrong_depth_and_missing_files_are_named(tmp_path):
    torch.save(_reference().state_dict(), tmp_path / "r18.pth")
    with pytest.raises(ValueError, match=r"r18\.pth does not fit a ResNet-50"):
        _loaded(str(tmp_path / "r18.pth"), depth=50, blocks=())
    with pytest.raises(FileNotFoundError, match="missing.pth"):
        _loaded(str(tmp_path / "missing.pth"))
    torch.save({"not": "weights"}, tmp_path / "junk.pth")
    with pytest.raises(ValueError, match=r"junk\.pth holds no state dict"):
        _loaded(str(tmp_path / "junk.pth"))


def test_named_torchvision_source_reads_torchs_hub_cache(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    name = pretrained.needed_file("torchvision:IMAGENET1K_V1", 18)
    assert name == "resnet18-f37072fd.pth"  # the file torchvision itself caches
    reference = _reference(blocks=(2, 2, 2, 2))
    (tmp_path / "checkpoints").mkdir()
    torch.save(reference.state_dict(), tmp_path / "checkpoints" / name)
    monkeypatch.setattr(torch.hub, "download_url_to_file", _no_network)
    pretrained.ensure_available(ImageEncoderConfig(depth=18, pretrained="torchvision:IMAGENET1K_V1"))
    _assert_same(_loaded("torchvision:IMAGENET1K_V1", blocks=()), reference)


def _no_network(url, *args, **kwargs):
    raise OSError(f"<urlopen error [Errno -3] Temporary failure in name resolution> {url}")


@pytest.mark.parametrize("setting, file", [
    ("torchvision:IMAGENET1K_V1", "resnet18-f37072fd.pth"),
    ("https://example.org/models/htc_r50_nuim.pth", "htc_r50_nuim.pth"),
])  # fmt: skip
def test_offline_named_sources_fail_in_one_line_naming_the_file_and_the_setting(tmp_path, monkeypatch, setting, file):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.setattr(torch.hub, "download_url_to_file", _no_network)
    with pytest.raises(pretrained.PretrainedUnavailable) as error:
        pretrained.ensure_available(ImageEncoderConfig(depth=18, pretrained=setting))
    message = str(error.value)
    assert "\n" not in message and file in message and "model.image.pretrained=PATH" in message
    assert str(tmp_path / "checkpoints") in message


def test_unknown_torchvision_weights_list_the_members():
    with pytest.raises(ConfigError, match="IMAGENET1K_V1"):
        pretrained.needed_file("torchvision:IMAGENET9K", 50)


def test_freezing_a_random_backbone_is_refused_with_the_reason():
    with pytest.raises(ConfigError, match=r"norm_eval freezes a randomly initialised backbone.*mean 0, variance 1"):
        pretrained.initialise(ResNetBackbone(ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1))))
    with pytest.raises(ConfigError, match="frozen_stages"):
        pretrained.initialise(ResNetBackbone(ImageEncoderConfig(**TINY, frozen_stages=1)))
    # Whole-model weights bring the backbone's statistics: then freezing is what the references do.
    pretrained.initialise(ResNetBackbone(ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1))), whole_model_weights=True)


def test_every_zoo_entry_can_start():
    """A paper entry names its weights; a CPU entry trains from scratch, so it must not freeze its statistics."""
    for name in zoo.names():
        experiment = zoo.experiment(name)
        settings = pretrained.backbone_settings(experiment.model)
        if "_tiny" in name:
            assert not settings, name
            model = zoo.build(name)
            pretrained.initialise(model)  # no error: nothing frozen at random
        elif "image" in {f for f in vars(experiment.model)} and experiment.model.image is not None:
            assert settings, f"{name} starts its backbone from random weights"
