"""``data.on_error=skip``: training refills its batches, evaluation and prediction pass over frames that fail.

A broken sample in training is replaced by the next index of the split that loads, with the augmentation draws of
the index it stands in for, so batches stay full and a run stays a pure function of (seed, epoch, index). In
evaluation a frame cannot be replaced (it would be scored twice): the batch holds the frames that loaded, an empty
batch is passed over, and the number of skipped frames is reported. Everything at batch size 1, where every failure
empties a batch.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import torch

from occkit.cli import main
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset, SampleError
from occkit.data.transforms import BevAugConfig, ImageAugConfig
from occkit.engine.evaluate import evaluate_model, evaluation_dataset, load_trained
from occkit.engine.train import train
from occkit.zoo import load_experiment

REPO = Path(__file__).resolve().parents[1]
CAMERAS = ("CAM_FRONT", "CAM_BACK")
#: flashocc_tiny made smaller still (as in test_engine), batch size 1, validation at the last step.
SMALL = (
    "data.cameras=[CAM_FRONT, CAM_BACK]",
    "data.image_aug.final_size=[64, 176]",
    "data.on_error=skip",
    "model.lss.image_size=[64, 176]",
    "model.image.out_stages=[3]",
    "model.bev.channels=[16, 32, 64]",
    "model.bev.neck_channels=16",
    "model.occupancy.in_channels=16",
    "model.occupancy.hidden_channels=16",
    "train.batch_size=1",
    "train.accumulate=1",
    "train.workers=0",
    "train.epochs=2",
    "train.max_steps=0",
    "train.log_every=1",
    "train.warmup_steps=1",
    "train.ema_decay=0",
    "train.val_every=0",
    "train.val_split=val",
    "train.checkpoint_every=0",
    "train.seed=0",
)


@pytest.fixture(scope="module")
def data(tmp_path_factory, synthetic_world) -> Path:
    """2 scenes x 3 key frames (scene-0001 trains, scene-0002 validates); one frame of each split is broken."""
    root = synthetic_world(copy_to=tmp_path_factory.mktemp("on_error") / "data", scenes=2, frames=3, seed=0,
                           image_size=(176, 99), cameras=CAMERAS)
    records = OccupancyDataset(DatasetConfig(root=str(root), split="all", cameras=CAMERAS, sweeps=-1)).records
    (root / records[1].cameras["CAM_BACK"].path).unlink()  # train split, index 1
    image = root / records[4].cameras["CAM_FRONT"].path  # val split, index 1
    image.write_bytes(image.read_bytes()[:-600])  # a truncated JPEG
    return root


def _dataset(root: Path, **options) -> OccupancyDataset:
    defaults = {"root": str(root), "split": "train", "cameras": CAMERAS, "sweeps": 0, "on_error": "skip",
                "image_aug": ImageAugConfig(final_size=(64, 176))}  # fmt: skip
    return OccupancyDataset(DatasetConfig(**{**defaults, **options}))


def test_an_all_skipped_batch_is_empty_not_an_error(data):
    dataset = _dataset(data)
    assert dataset[1] is None and dataset.skipped == 1
    empty = collate([dataset[1]])
    assert len(empty) == 0 and empty.tokens == [] and empty.images is None
    with pytest.raises(SampleError, match="image not found"):
        _dataset(data, on_error="raise")[1]


def test_refill_replaces_a_failed_sample_by_the_next_that_loads(data, caplog):
    augment = {"augment": True, "bev_aug": BevAugConfig(flip_x=0.5, flip_y=0.5, rotate_deg=(-20.0, 20.0))}
    dataset = _dataset(data, **augment)
    dataset.refill = True
    with caplog.at_level(logging.WARNING, logger="occkit.data.dataset"):
        sample = dataset[1]
    assert sample.token == dataset.records[2].token and dataset.replaced == 1 and dataset.skipped == 1
    assert f"sample {dataset.records[1].token} (index 1) replaced by sample {sample.token} (index 2)" in caplog.text
    # A pure function of (seed, epoch, index): another dataset gives the same sample, with the draws of index 1.
    other = _dataset(data, **augment)
    other.refill = True
    again = other[1]
    assert torch.equal(again.images, sample.images) and torch.equal(again.bev_aug, sample.bev_aug)
    assert not torch.equal(other[2].bev_aug, sample.bev_aug)  # not the draws of index 2
    other.set_epoch(1)
    assert other[1].token == sample.token
    # Nothing loads: an error, not an endless search.
    hopeless = _dataset(data, sweeps=9, split="val", cameras=("CAM_FRONT",))
    hopeless.refill = True
    for record in hopeless.records:
        (data / record.cameras["CAM_FRONT"].path).rename(data / f"{record.token}.jpg")
    try:
        with pytest.raises(SampleError, match="no sample of split 'val' loads"):
            hopeless[0]
    finally:
        for record in hopeless.records:
            (data / f"{record.token}.jpg").rename(data / record.cameras["CAM_FRONT"].path)


@pytest.fixture(scope="module")
def run(data, tmp_path_factory) -> tuple[Path, dict]:
    """A training run at batch size 1 over the broken splits: its folder and validation metrics."""
    experiment = load_experiment(REPO / "configs" / "flashocc_tiny.yaml", [f"data.root={data}", *SMALL])
    out = tmp_path_factory.mktemp("run") / "run"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = train(experiment, out, progress=False, device="cpu")
    finally:
        torch.set_num_threads(threads)
    return out, {"steps": result.steps, "metrics": result.metrics}


def test_training_refills_and_validation_passes_over_skipped_frames(run):
    out, result = run
    assert result["steps"] == 6  # 2 epochs x 3 full batches of one sample: the broken one was replaced
    metrics = result["metrics"]
    assert metrics["frames"] == 2 and metrics["skipped"] == 1
    assert [json.loads(line)["skipped"] for line in (out / "val.jsonl").read_text().splitlines()] == [1]


def test_evaluation_at_batch_size_1_scores_the_frames_that_load(data, run):
    out, _ = run
    model, experiment = load_trained(out / "best.pt")
    dataset = evaluation_dataset(experiment, None, "val")
    seen = []
    result = evaluate_model(model, dataset, batch_size=1, progress=seen.append)
    assert result["frames"] == 2 and result["skipped"] == 1 and seen == [1, 1, 1]
    whole = evaluate_model(model, dataset, batch_size=2)
    assert whole["frames"] == 2 and whole["skipped"] == 1 and whole["miou"] == result["miou"]


def test_cli_eval_and_predict_pass_over_the_broken_frame(data, run, tmp_path, capsys):
    out, _ = run
    common = ["--ckpt", str(out / "best.pt"), "--workers", "0", "--device", "cpu", "--batch-size", "1"]
    assert main(["eval", *common, "--out", str(tmp_path / "eval"), "--no-rayiou"]) == 0
    assert json.loads((tmp_path / "eval" / "metrics.json").read_text())["skipped"] == 1
    assert main(["predict", *common, "--data", str(data), "--split", "val", "--out", str(tmp_path / "preds")]) == 0
    records = _dataset(data, split="val").records
    written = sorted(path.stem for path in (tmp_path / "preds").glob("*.npz"))
    assert written == sorted(r.token for i, r in enumerate(records) if i != 1)
    capsys.readouterr()


def test_eval_writes_no_prediction_outside_its_folder(data, run, tmp_path):
    out, _ = run
    model, experiment = load_trained(out / "best.pt")
    dataset = evaluation_dataset(experiment, None, "val")
    object.__setattr__(dataset.records[0], "token", "../../escape_tok")  # as if made around the index's checks
    predictions = tmp_path / "deep" / "preds"
    predictions.mkdir(parents=True)
    with pytest.raises(ValueError, match=r"'\.\./\.\./escape_tok' is not a safe name"):
        evaluate_model(model, dataset, batch_size=1, predictions=predictions)
    assert not list(tmp_path.rglob("escape_tok*"))



# ------------------------------------------------------------------------------ errors in DataLoader workers
class _BrokenSamples(torch.utils.data.Dataset):
    """Sample 1 fails as a broken file would: a ValueError naming the sample, or an error torch cannot rebuild."""

    def __init__(self, error: str = "value") -> None:
        self.error = error

    def __len__(self) -> int:
        return 3

    def __getitem__(self, index: int) -> int:
        if index == 1 and self.error == "value":
            raise ValueError("sample tok-1: CAM_FRONT image samples/CAM_FRONT/tok-1.jpg is truncated")
        if index == 1:
            b"\xff".decode()  # UnicodeDecodeError takes five arguments: torch cannot rebuild it from a message
        return index


def _raised(loader) -> BaseException:
    with pytest.raises(Exception) as raised:
        list(loader)
    return raised.value


@pytest.mark.parametrize("error", ["value", "decode"])
def test_a_worker_error_is_raised_as_with_no_workers(error):
    from occkit.data.loader import WorkerTraceback, sample_loader
    from occkit.errors import is_input_error, one_line

    dataset = _BrokenSamples(error)
    inline = _raised(sample_loader(dataset, batch_size=1, num_workers=0, collate_fn=list))
    in_worker = _raised(sample_loader(dataset, batch_size=1, num_workers=1, collate_fn=list))
    assert type(in_worker) is type(inline) and str(in_worker) == str(inline) and is_input_error(in_worker)
    assert "DataLoader worker" not in one_line(in_worker) and len(one_line(in_worker)) < 100
    # --debug shows where the worker failed: its traceback is the cause of the error raised again.
    assert isinstance(in_worker.__cause__, WorkerTraceback) and "__getitem__" in str(in_worker.__cause__)


def test_a_plain_dataloader_worker_error_still_prints_as_one_line():
    from occkit.errors import one_line

    raised = _raised(torch.utils.data.DataLoader(_BrokenSamples(), batch_size=1, num_workers=1))
    assert "Caught ValueError in DataLoader worker process 0" in str(raised)  # torch's message, kilobytes long
    assert one_line(raised) == "sample tok-1: CAM_FRONT image samples/CAM_FRONT/tok-1.jpg is truncated"


def test_cli_train_with_a_loader_worker_reports_a_broken_sample_in_one_line(data, tmp_path, capsys):
    settings = [s for s in SMALL if not s.startswith(("data.on_error", "train.workers"))]
    settings += ["data.on_error=raise", "train.workers=1", f"data.root={data}"]
    argv = ["train", "--config", str(REPO / "configs" / "flashocc_tiny.yaml"), "--out", str(tmp_path / "run"),
            "--device", "cpu", "--no-progress", *(f"--set={s}" for s in settings)]  # fmt: skip
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("occkit train: error: "), lines
    assert "image not found" in lines[0] and "DataLoader worker" not in lines[0] and "Traceback" not in lines[0]
