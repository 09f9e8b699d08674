"""Every zoo entry builds, matches its YAML twin, trains one step and predicts in its own label space (the paper
entries of ``STEPPED_ELSEWHERE``: what they change, at small size, here or in their architecture's tests).

The paper entries run at their own input size on one sample with two cameras (the camera count is free, the image
size is fixed by the depth frustum) and 2000 LiDAR points, so that the whole zoo fits in the suite's time budget.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import make_batch, parameters_without_gradient

from occkit import zoo
from occkit.label_space import label_space
from occkit.models.complexity import count_parameters

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", zoo.names())
def test_every_zoo_entry_builds_and_matches_its_yaml(name):
    model = zoo.build(name)
    assert count_parameters(model) > 0
    path = CONFIGS / f"{name}.yaml"
    assert path.read_text() == zoo.config_yaml(name), f"{path} is stale: regenerate it with scripts/write_configs.py"
    assert zoo.load_experiment(path) == zoo.experiment(name)


#: Paper-size entries whose only difference from an entry stepped here is a switch, a schedule or a label space that
#: a smaller model steps elsewhere: a full-size step of each would cost the suite minutes and test nothing more.
#: Entry -> what steps its difference.
STEPPED_ELSEWHERE = {
    "daocc_24e": "nothing to step: the schedule differs, the model is daocc's",
    "daocc_lidar": "DAOcc without its camera branch: test_daocc steps daocc_tiny's without one",
    "flashocc_m1": "M0's structure with other widths: flashocc_m0 here, and test_reference_parity_models runs both "
                   "against the reference",
    "daocc_no_mask": "the unmasked loss: daocc_surroundocc_tiny here, test_losses",
    "daocc_no_detection": "test_daocc (the detachable head), test_export (DAOcc without the head)",
    "daocc_no_range_extension": "another BEV range and grid: daocc_tiny's +-43.2 m here",
    "daocc_surroundocc": "SurroundOcc's grid, frame and classes at DAOcc's structure: daocc_surroundocc_tiny here",
    "da_occ_no_mask": "the unmasked loss and affinities: test_da_occ, test_losses",
    "da_occ_depth": "the camera-aware DepthNet and depth BCE: test_da_occ",
    "da_occ_height4": "the height grid of Table II: test_da_occ",
    "da_occ_no_dac": "every DAC switched off: test_da_occ",
    "da_occ_dac_height_only": "the BEV DACs switched off: test_da_occ",
    "da_occ_1f": "the concatenated history: test_temporal_models (DA-Occ and FlashOcc at small size)",
    "da_occ_16f": "the concatenated history (here of 16 frames): test_temporal_models (DA-Occ and FlashOcc at small "
                  "size)",
    "da_occ_16f_recurrent": "the recurrent history: da_occ_tiny_temporal here, test_temporal_models",
    "flashocc_m0_4d": "BEVDet4D's concatenated history on FlashOcc: test_temporal_models",
    "flashocc_pano": "flashocc_m0 with the panoptic switch (centre head, instances): flashocc_tiny_pano here, "
                     "test_panoptic",
}

#: Entries that are neither CPU-sized nor a published row, and why.
NO_PAPER_ROW = {
    "daocc_lidar": "DAOcc without its camera branch",
    "flashocc_m0_4d": "FlashOcc publishes its temporal models with stereo depth only (M2, 4D-Stereo)",
    "da_occ_16f_recurrent": "da_occ_16f's history as a recurrent state: occkit's constant-cost variant of the row",
}


def test_every_entry_left_out_of_the_step_test_is_a_paper_size_entry():
    assert set(STEPPED_ELSEWHERE).issubset(zoo.names())
    assert not any("tiny" in name for name in STEPPED_ELSEWHERE)


@pytest.mark.parametrize("name", [name for name in zoo.names() if name not in STEPPED_ELSEWHERE])
def test_every_zoo_entry_trains_a_step_and_predicts_its_label_space(name):
    experiment = zoo.experiment(name)
    space = label_space(experiment.data.label_space)
    batch = make_batch(
        batch_size=1,
        num_cameras=min(2, len(experiment.data.cameras)),
        image_size=tuple(experiment.data.image_aug.final_size),
        num_points=2000,
        depth_stride=experiment.data.depth_downsample,
        space=space,
        history=experiment.data.history,
        flow=experiment.data.flow,
    )
    torch.manual_seed(0)
    model = zoo.build(name).train()

    # A model trained on streams (a recurrent history) takes its history from a memory, as the trainer gives it.
    streamed = model.temporal is not None and model.temporal.cfg.streamed_training
    losses = model.loss(model(batch, memory=model.stream()) if streamed else model(batch), batch)
    assert losses and all(torch.isfinite(value) for value in losses.values()), losses
    sum(losses.values()).backward()
    missing = parameters_without_gradient(model)
    if not experiment.data.cameras:  # a LiDAR-only model holds no camera branch to leave without gradient
        assert not any(name.startswith(("image", "view")) for name, _ in model.named_parameters())
    assert not missing, f"{name}: no gradient for {missing}"

    model.eval()
    with torch.no_grad():
        prediction = model.predict(batch)
    semantics = prediction.semantics
    assert semantics.dtype == torch.uint8 and tuple(semantics.shape) == (1, *space.grid.shape)
    assert int(semantics.max()) < space.num_classes
    assert (prediction.flow is not None) == experiment.data.flow == (experiment.model.flow is not None)


def test_every_paper_entry_names_its_row_in_its_header_and_in_the_reproducing_guide():
    guide = (CONFIGS.parent / "docs" / "reproducing.md").read_text()
    rows = {name: zoo.paper_row(name) for name in zoo.names()}
    assert {"daocc", "flashocc_m0", "flashocc_m1", "da_occ"} <= {name for name, row in rows.items() if row}
    for name, row in rows.items():
        header = "".join(line.lstrip("#").strip() + " " for line in zoo.config_yaml(name).splitlines()
                         if line.startswith("#"))  # fmt: skip
        if row is None:
            assert "_tiny" in name or name in NO_PAPER_ROW, f"{name} reproduces no paper row"
            continue
        assert f"| `{name}` |" in guide, f"docs/reproducing.md does not list {name}"
        assert row.result in " ".join(header.split()), f"{name}'s config header does not name {row.result}"


@pytest.mark.parametrize("name", zoo.names())
def test_what_supervises_an_entry_in_training_is_what_its_data_loads(name):
    experiment = zoo.experiment(name)
    targets = experiment.model.training_targets
    box_heads = (getattr(experiment.model, "detection", None), getattr(experiment.model, "instances", None))
    assert ("3D boxes" in targets) == any(head is not None for head in box_heads)  # DAOcc's detection, panoptic centres
    if "3D boxes" in targets:
        assert experiment.data.boxes
    if any(target.startswith("LiDAR") for target in targets):
        assert experiment.data.depth_downsample > 0 and experiment.data.sweeps >= 0
    assert not set(targets) & set(experiment.model.sensors)


def test_training_targets_follow_the_switches():
    assert zoo.model_config("daocc_no_detection")[1].training_targets == ()
    assert zoo.model_config("da_occ_depth")[1].training_targets == ("LiDAR depth", "LiDAR heights")
    assert zoo.model_config("da_occ_tiny")[1].training_targets == ("LiDAR heights",)
    assert zoo.model_config("flashocc_tiny")[1].training_targets == ()


def test_zoo_diff_lists_the_settings_an_entry_changes_and_the_cli_prints_them(capsys):
    from occkit.cli import main

    assert zoo.diff("flashocc_m0", "flashocc_m1") == [
        ("model.bev.neck_channels", 128, 256),
        ("model.lss.depth_range", [1.0, 45.0, 1.0], [1.0, 45.0, 0.5]),
        ("model.occupancy.hidden_channels", 128, 256),
        ("model.occupancy.in_channels", 128, 256),
    ]
    assert zoo.diff("daocc", "daocc") == []
    ((_, before, after),) = [d for d in zoo.diff("daocc", "daocc_no_detection") if d[0] == "model.detection"]
    assert isinstance(before, dict) and after is None
    assert main(["zoo", "diff", "daocc", "daocc_no_detection"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "daocc_no_detection differs from daocc in 2 setting(s):",
        "  data.boxes: True -> False",
        f"  model.detection: {{...}} ({len(before)} settings) -> None",
    ]
    assert main(["zoo", "diff", "daocc"]) == 2
    assert "occkit zoo diff takes two entries, got 1" in capsys.readouterr().err
    assert main(["zoo", "list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listed] == zoo.names()


def test_an_entry_registers_once_under_its_function_name():
    from occkit.zoo.registry import ENTRIES, preset

    assert ENTRIES["daocc_tiny"].architecture == "daocc" and ENTRIES["daocc_tiny"].make.__name__ == "daocc_tiny"
    with pytest.raises(ValueError, match="zoo entry 'daocc_tiny' is registered twice"):
        preset("daocc")(ENTRIES["daocc_tiny"].make)
