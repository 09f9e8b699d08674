"""Typed configs: YAML round trips, dotted overrides, and errors that name the key."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from occkit.config import (
    ConfigError,
    apply_overrides,
    dump_yaml,
    field_docs,
    from_dict,
    load_config,
    save_config,
    to_dict,
)


@dataclass(frozen=True)
class OptimConfig:
    lr: float = 1e-4
    """Peak learning rate of AdamW."""
    betas: tuple[float, float] = (0.9, 0.999)
    """Adam moment coefficients."""
    schedule: Literal["cosine", "constant"] = "cosine"
    """Learning-rate schedule."""


@dataclass(frozen=True)
class DataConfig:
    cameras: tuple[str, ...] = ("CAM_FRONT", "CAM_BACK")
    """Cameras to load, in order."""
    root: str | None = None
    """Dataset root; None means the synthetic world."""
    image_size: tuple[int, int] = (256, 704)


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 24
    """Training epochs."""
    amp: bool = False
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimiser settings."""
    data: DataConfig = field(default_factory=DataConfig)

    def __post_init__(self):
        if self.epochs < 1:
            raise ValueError(f"epochs must be >= 1, got {self.epochs}")


@dataclass(frozen=True)
class Required:
    name: str
    size: int = 1


def test_round_trip_through_yaml_file(tmp_path):
    cfg = TrainConfig(epochs=3, optim=OptimConfig(lr=2e-4), data=DataConfig(cameras=("CAM_FRONT",), root="data"))
    path = save_config(cfg, tmp_path / "sub" / "train.yaml")
    assert load_config(TrainConfig, path) == cfg
    assert path.read_text().startswith("# Training epochs.\nepochs: 3\n")


def test_dump_writes_field_docs_as_comments():
    text = dump_yaml(TrainConfig())
    assert "  # Peak learning rate of AdamW.\n  lr: 0.0001\n" in text
    assert "# Optimiser settings.\noptim:\n" in text
    assert field_docs(OptimConfig)["betas"] == "Adam moment coefficients."
    assert "amp" not in field_docs(TrainConfig)


def test_to_dict_gives_plain_lists():
    assert to_dict(TrainConfig())["optim"] == {"lr": 1e-4, "betas": [0.9, 0.999], "schedule": "cosine"}


def test_from_dict_fills_defaults_and_converts_types():
    cfg = from_dict(TrainConfig, {"optim": {"lr": 1, "betas": [0.8, 0.9]}, "data": {"image_size": [128, 352]}})
    assert cfg.optim.lr == 1.0 and isinstance(cfg.optim.lr, float)
    assert cfg.optim.betas == (0.8, 0.9)
    assert cfg.data.image_size == (128, 352)
    assert cfg.epochs == 24


def test_overrides_parse_yaml_values():
    cfg = apply_overrides(
        TrainConfig(),
        ["optim.lr=3e-4", "epochs=6", "amp=true", "data.cameras=[CAM_FRONT_LEFT]", "data.root=/data/nuscenes"],
    )
    assert cfg.optim.lr == 3e-4
    assert cfg.epochs == 6
    assert cfg.amp is True
    assert cfg.data.cameras == ("CAM_FRONT_LEFT",)
    assert cfg.data.root == "/data/nuscenes"
    assert apply_overrides(cfg, ["data.root=null"]).data.root is None


def test_load_applies_overrides_after_the_file(tmp_path):
    path = tmp_path / "train.yaml"
    path.write_text("epochs: 2\noptim:\n  lr: 0.001\n")
    cfg = load_config(TrainConfig, path, overrides=["optim.lr=0.002"])
    assert (cfg.epochs, cfg.optim.lr) == (2, 0.002)


def test_unknown_key_lists_valid_keys_and_suggests(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("optim:\n  lrr: 0.1\n")
    with pytest.raises(ConfigError) as error:
        load_config(TrainConfig, path)
    message = str(error.value)
    assert str(path) in message and ".optim" in message
    assert "'lrr'" in message and "did you mean 'lr'" in message
    assert "valid keys: lr, betas, schedule" in message


def test_unknown_override_key_lists_valid_keys():
    with pytest.raises(ConfigError, match=r"unknown key 'optimizer'.*valid keys: epochs, amp, optim, data"):
        apply_overrides(TrainConfig(), ["optimizer.lr=1"])
    with pytest.raises(ConfigError, match=r"unknown key 'momentum'.*valid keys: lr, betas, schedule"):
        apply_overrides(TrainConfig(), ["optim.momentum=0.9"])
    with pytest.raises(ConfigError, match="epochs is a value, not a section"):
        apply_overrides(TrainConfig(), ["epochs.x=1"])
    with pytest.raises(ConfigError, match="must look like key.sub=value"):
        apply_overrides(TrainConfig(), ["epochs"])


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("epochs=two", r"config \(after --set\)\.epochs: expected int, got 'two'"),
        ("epochs=2.5", r"\.epochs: expected int, got 2.5"),
        ("epochs=true", r"\.epochs: expected int, got True"),
        ("amp=1", r"\.amp: expected bool, got 1"),
        ("optim.lr=fast", r"\.optim\.lr: expected float, got 'fast'"),
        ("optim.betas=[0.9]", r"\.optim\.betas: expected 2 values"),
        ("optim.schedule=step", r"\.optim\.schedule: 'step' is not one of 'cosine', 'constant'"),
        ("data.cameras=CAM_FRONT", r"\.data\.cameras: expected a list"),
        ("data.image_size=[1, x]", r"\.data\.image_size\[1\]: expected int"),
        ("optim=3", r"\.optim: expected a mapping for OptimConfig"),
    ],
)
def test_wrong_types_name_the_key(override, expected):
    with pytest.raises(ConfigError, match=expected):
        apply_overrides(TrainConfig(), [override])


def test_validation_in_post_init_names_the_source(tmp_path):
    path = tmp_path / "train.yaml"
    path.write_text("epochs: 0\n")
    with pytest.raises(ConfigError, match=r"train.yaml: epochs must be >= 1, got 0"):
        load_config(TrainConfig, path)


def test_missing_required_key_and_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="missing required keys: name"):
        from_dict(Required, {"size": 2})
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(TrainConfig, tmp_path / "absent.yaml")
    (tmp_path / "broken.yaml").write_text("epochs: [1\n")
    with pytest.raises(ConfigError, match="broken.yaml: not valid YAML"):
        load_config(TrainConfig, tmp_path / "broken.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="list.yaml: expected a mapping for TrainConfig"):
        load_config(TrainConfig, tmp_path / "list.yaml")


def test_empty_file_gives_defaults(tmp_path):
    (tmp_path / "empty.yaml").write_text("")
    assert load_config(TrainConfig, tmp_path / "empty.yaml") == TrainConfig()


def test_configs_are_frozen():
    with pytest.raises(AttributeError):
        TrainConfig().epochs = 3  # type: ignore[misc]
