"""Shipped weights: written at half precision with a card, checked against the card's hash on every load, and taken by
``zoo.build(weights="synthetic")`` and by every command that runs a model (``--weights synthetic --model ENTRY``).

The weights here are a random model's, written into a temporary folder that stands in for the package's; the
trained files and their scores are checked by test_shipped_scores.py.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from occkit import shipped, zoo
from occkit.cli import main
from occkit.config import ConfigError
from occkit.model_source import ModelSource

ENTRY = "flashocc_tiny"
WORLD = {"seed": 5, "scenes": 2, "frames": 2, "image_size": [176, 99]}


def card_fields(entry: str = ENTRY) -> dict:
    return {"entry": entry, "world": WORLD, "steps": 3, "train_seconds": 1.5, "device": "cpu, 1 thread",
            "command": "pytest", "scores": {"miou": 0.0, "iou": 0.0, "rayiou": None, "per_class": {}}}  # fmt: skip


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> tuple[Path, torch.nn.Module]:
    """A folder with random weights of ``flashocc_tiny`` and their card, and the model they came from."""
    folder = tmp_path_factory.mktemp("weights")
    torch.manual_seed(0)
    model = zoo.build(ENTRY)
    shipped.write_shipped(model, "flashocc", card_fields(), folder)
    return folder, model


@pytest.fixture
def installed(weights, monkeypatch) -> Path:
    """The temporary folder in place of the package's."""
    monkeypatch.setattr(shipped, "weights_folder", lambda: weights[0])
    return weights[0]


def test_weights_are_stored_at_half_precision_and_load_into_the_float_model(weights):
    folder, model = weights
    card = shipped.card(ENTRY, folder)
    assert card.sha256 == __import__("hashlib").sha256((folder / f"{ENTRY}.safetensors").read_bytes()).hexdigest()
    assert card.world == WORLD and card.occkit_version
    assert (folder / f"{ENTRY}.safetensors").stat().st_size < 0.6 * 4 * sum(p.numel() for p in model.parameters())
    loaded = shipped.load_shipped(zoo.build(ENTRY), ENTRY, folder)
    for key, value in model.state_dict().items():
        expected = value.half().float() if value.is_floating_point() else value
        assert torch.equal(loaded.state_dict()[key], expected), key
    assert next(loaded.parameters()).dtype == torch.float32


def test_zoo_build_takes_the_shipped_weights(installed, weights):
    model = zoo.build(ENTRY, weights="synthetic")
    reference = weights[1].state_dict()["occupancy_head.predictor.2.weight"].half().float()
    assert torch.equal(model.state_dict()["occupancy_head.predictor.2.weight"], reference)


def test_a_file_other_than_its_cards_is_refused(weights, tmp_path):
    folder = tmp_path / "changed"
    folder.mkdir()
    for path in weights[0].iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    data = bytearray((folder / f"{ENTRY}.safetensors").read_bytes())
    data[-1] ^= 1
    (folder / f"{ENTRY}.safetensors").write_bytes(bytes(data))
    with pytest.raises(ConfigError, match="not the file its card describes"):
        shipped.load_shipped(zoo.build(ENTRY), ENTRY, folder)


def test_an_entry_without_shipped_weights_names_those_with(installed):
    with pytest.raises(ConfigError, match=f"no trained weights for daocc_tiny .*has: {ENTRY}"):
        zoo.build("daocc_tiny", weights="synthetic")


def test_the_model_source_names_its_file_and_label(installed):
    source = ModelSource(weights="synthetic", entry=ENTRY)
    assert source.file == installed / f"{ENTRY}.safetensors"
    assert source.label == f"{ENTRY}, synthetic weights"
    with pytest.raises(ValueError, match="per zoo entry"):
        ModelSource(weights="synthetic")
    with pytest.raises(ValueError, match="exactly one"):
        ModelSource()


def test_cli_synthetic_weights_need_a_shipped_model(installed, tmp_path, capsys):
    out = tmp_path / "p"
    assert main(["predict", "--weights", "synthetic", "--data", str(tmp_path), "--out", str(out)]) == 2
    assert "--weights synthetic needs --model ENTRY (shipped: flashocc_tiny)" in capsys.readouterr().err
    assert main(["predict", "--weights", "synthetic", "--model", "da_occ_tiny", "--data", str(tmp_path),
                 "--out", str(out)]) == 2  # fmt: skip
    assert "occkit ships no trained weights for da_occ_tiny" in capsys.readouterr().err
    assert main(["predict", "--ckpt", str(tmp_path / "x.pt"), "--model", ENTRY, "--data", str(tmp_path),
                 "--out", str(out)]) == 2  # fmt: skip


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """2 scenes x 2 key frames (scene-0002 is the val split), six cameras."""
    from occkit.sim.generate import SimConfig, simulate_dataset

    root = tmp_path_factory.mktemp("world") / "data"
    simulate_dataset(SimConfig(scenes=2, frames=2, seed=5, image_size=(352, 198)), root)
    return root


def test_every_command_that_runs_a_model_takes_the_shipped_weights(installed, world, tmp_path):
    model = ["--weights", "synthetic", "--model", ENTRY]
    assert main(["predict", *model, "--data", str(world), "--out", str(tmp_path / "pred"), "--workers", "0"]) == 0
    predictions = sorted((tmp_path / "pred").glob("*.npz"))
    assert len(predictions) == 2
    assert main(["eval", *model, "--data", str(world), "--out", str(tmp_path / "eval"), "--workers", "0",
                 "--no-rayiou"]) == 0  # fmt: skip
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["frames"] == 2 and metrics["checkpoint"] == f"synthetic ({ENTRY})"
    assert main(["viz", *model, "--data", str(world), "--frames", "1", "--out", str(tmp_path / "viz")]) == 0
    index = json.loads((tmp_path / "viz" / "index.json").read_text())
    assert index["predictions"] == f"synthetic ({ENTRY})" and "compare" in index["frames"][0]["files"]
    assert main(["view", *model, "--data", str(world), "--frames", "1", "--save", str(tmp_path / "scene.rrd")]) == 0
    assert (tmp_path / "scene.rrd").stat().st_size > 0
    assert main(["robustness", *model, "--data", str(world), "--out", str(tmp_path / "rob"), "--suite", "fog:1",
                 "--no-rayiou", "--workers", "0"]) == 0  # fmt: skip
    report = json.loads((tmp_path / "rob" / "robustness.json").read_text())
    assert report["checkpoint"] == f"synthetic ({ENTRY})"


def _training_script():
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "scripts" / "train_shipped_weights.py"
    spec = importlib.util.spec_from_file_location("train_shipped_weights", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_a_run_converges_only_on_a_plateau_of_enough_validations():
    script = _training_script()

    def points(values):
        return [{"step": 100 * (i + 1), "miou": v, "iou": 0.6} for i, v in enumerate(values)]

    plateau, _ = script.converged(points([0.10, 0.15, 0.16, 0.162, 0.163]))  # +0.1 over the last fifth
    rising, gain = script.converged(points([0.10, 0.15, 0.20, 0.25, 0.30]))
    assert plateau and not rising and gain == pytest.approx(0.05)
    assert script.converged(points([0.10, 0.09, 0.08])) == (False, pytest.approx(float("nan"), nan_ok=True))


def test_a_card_says_where_it_stands_against_its_target(tmp_path):
    script = _training_script()
    curve = [{"step": 100 * (i + 1), "miou": v, "iou": 0.6} for i, v in enumerate([0.10, 0.15, 0.16, 0.162, 0.163])]
    objects = {"car": 0.2, "bus": 0.3, "truck": 0.01, "pedestrian": 0.0}
    below = script.card_notes("da_occ_tiny", curve, {"miou": 0.239, "per_class": objects})
    assert below == ("converged: +0.10 mIoU over the last fifth of the run; 23.9 mIoU on the demo world's held-out "
                     "frames, below its target of 25; 0 IoU on pedestrian")  # fmt: skip
    met = script.card_notes("flashocc_tiny", curve[:3], {"miou": 0.25, "per_class": {**objects, "pedestrian": 0.02}})
    assert met == ("not converged: 3 held-out validations, too few to tell; 25.0 mIoU on the demo world's held-out "
                   "frames, meeting its target of 20")  # fmt: skip
    # --refresh-notes rewrites only the notes: the weights and the hash the card holds of them stay.
    for name in ("flashocc_tiny.card.json", "flashocc_tiny.safetensors"):
        shutil.copy(shipped.weights_folder() / name, tmp_path / name)
    before = json.loads((tmp_path / "flashocc_tiny.card.json").read_text())
    written = script.refresh_notes("flashocc_tiny", tmp_path)
    after = json.loads((tmp_path / "flashocc_tiny.card.json").read_text())
    assert after == {**before, "notes": written} and shipped.card("flashocc_tiny", tmp_path).notes == written
    assert shipped.weights_path("flashocc_tiny", tmp_path).is_file()


def test_a_card_names_every_device_a_run_trained_on(tmp_path):
    script = _training_script()
    assert script.devices(tmp_path, 500, "cpu (2 threads)") == "cpu (2 threads)"  # no record: the session's own
    script.record_session(tmp_path, "NVIDIA H100")  # a fresh run starts at step 0
    torch.save({"optimizer": {"state": {}}}, tmp_path / "step-00002304.pt")
    script.record_session(tmp_path, "cpu (1 threads)")  # resumed from its newest checkpoint
    torch.save({"optimizer": {"state": {}}}, tmp_path / "step-00002400.pt")
    script.record_session(tmp_path, "cpu (1 threads)")
    assert script.devices(tmp_path, 3000, "?") == "NVIDIA H100 (steps 0-2304), cpu (1 threads) (steps 2304-3000)"
    assert script.devices(tmp_path, 2000, "?") == "NVIDIA H100 (steps 0-2000)"
    # A checkpoint that travelled without its optimizer state: the session after it says so.
    torch.save({"optimizer": None}, tmp_path / "step-00002600.pt")
    script.record_session(tmp_path, "cpu (1 threads)")
    assert script.devices(tmp_path, 3000, "?") == ("NVIDIA H100 (steps 0-2304), cpu (1 threads) (steps 2304-2600), "
                                                   "cpu (1 threads), resumed with fresh optimizer moments "
                                                   "(steps 2600-3000)")  # fmt: skip


def test_a_continued_run_adds_up_with_the_run_it_continues(tmp_path):
    """--continue-epochs: the shipped weights and card are kept in the new run's folder at its start, and the new card
    adds the two runs up: steps, time, devices, both commands, and one curve with the continuation's validations
    counted from the start of the first run."""
    from occkit.experiment import replace_train


    script = _training_script()
    original = shipped.card(ENTRY)
    run = script.continuation_folder(tmp_path, ENTRY, shipped.weights_folder())
    assert run == tmp_path / f"{ENTRY}-from-{original.steps}"  # a continuation of it gets a folder of its own
    base = script.start_continuation(ENTRY, run, shipped.weights_folder())
    assert base == original and (run / "base.safetensors").is_file()
    assert script.start_continuation(ENTRY, run, tmp_path / "elsewhere") == base  # a resumed start keeps its base
    (run / "val.jsonl").write_text("".join(json.dumps({"step": s, "miou": m, "iou": 0.6}) + "\n"
                                           for s, m in ((100, 0.30), (200, 0.31))))  # fmt: skip
    (run / "log.jsonl").write_text(json.dumps({"step": 200, "samples_per_s": 2.0}) + "\n")
    script.record_session(run, "cpu (2 threads)")
    experiment = replace_train(zoo.experiment(ENTRY), epochs=6, batch_size=4)
    fields = script.merged_card_fields(base, run, experiment, 200, "?")
    assert fields["steps"] == original.steps + 200
    assert fields["curve"][: len(original.curve)] == original.curve
    assert [p["step"] for p in fields["curve"][len(original.curve):]] == [original.steps + 100, original.steps + 200]
    assert fields["train_seconds"] == pytest.approx(original.train_seconds + 200 * 4 / 2.0, abs=0.1)
    assert fields["device"] == (f"{original.device}; then 6 more epochs from those weights (a new warm-up and cosine "
                                "schedule, fresh optimizer moments; steps counted from there): cpu (2 threads) "
                                "(steps 0-200)")  # fmt: skip
    continuation = f"python scripts/train_shipped_weights.py --entry {ENTRY} --continue-epochs 6 --batch-size 4 --write"
    assert fields["command"] == f"{original.command} && {continuation}"
