"""benchmarks/study.py: which runs are still to do, with seeds landing out of order, and when a claim gets a third."""

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BETTER, WORSE = "da_occ_tiny", "flashocc_tiny"  # the arms of the claim "DA-Occ beats FlashOcc at matched size"


@pytest.fixture(scope="module")
def study():
    """benchmarks/study.py as a module (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("benchmarks_study", REPO / "benchmarks" / "study.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _args(out: Path) -> argparse.Namespace:
    return argparse.Namespace(out=out, data=out / "world", arms=[BETTER, WORSE], seeds=2, max_seeds=3, commit=False,
                              jobs=1)


def _land(study, out: Path, arm: str, seed: int, miou: float) -> None:
    folder = out / study._slug(arm)
    folder.mkdir(parents=True, exist_ok=True)
    result = {"arm": arm, "seed": seed, "steps": 10, "miou": miou, "iou": 0.5, "rayiou": 0.1, "device": "CPU",
              "train_seconds": 60.0, "train_cpu_seconds": 120.0, "eval_seconds": 1.0, "eval_cpu_seconds": 2.0}
    (folder / f"seed-{seed}.json").write_text(json.dumps(result))


def test_a_seed_that_landed_first_is_not_run_again(study, tmp_path):
    _land(study, tmp_path, BETTER, 1, 0.2)  # seed 1 finished before seed 0 (runs in parallel)
    assert study._todo(_args(tmp_path), set()) == [(BETTER, 0), (WORSE, 0), (WORSE, 1)]
    assert study._todo(_args(tmp_path), {(BETTER, 0), (WORSE, 0)}) == [(WORSE, 1)]


@pytest.mark.parametrize(("worse", "third"), [((0.10, 0.12), False), ((0.10, 0.21), True)])
def test_a_third_seed_only_where_the_ranges_overlap(study, tmp_path, worse, third):
    for seed, miou in enumerate((0.20, 0.22)):
        _land(study, tmp_path, BETTER, seed, miou)
    for seed, miou in enumerate(worse):
        _land(study, tmp_path, WORSE, seed, miou)
    expected = [(BETTER, 2), (WORSE, 2)] if third else []
    assert study._todo(_args(tmp_path), set()) == expected


def test_run_all_runs_what_is_missing_and_rewrites_the_summary(study, tmp_path, monkeypatch):
    ran = []

    def fake_run(name, seed, args):
        ran.append((name, seed))
        _land(study, args.out, name, seed, 0.2 if name == BETTER else 0.1)

    monkeypatch.setattr(study, "run_arm", fake_run)
    _land(study, tmp_path, WORSE, 0, 0.1)
    study.run_all(_args(tmp_path))
    assert ran == [(BETTER, 0), (BETTER, 1), (WORSE, 1)]
    summary = json.loads((tmp_path / "study.json").read_text())
    assert json.dumps(summary).count("holds") >= 1
