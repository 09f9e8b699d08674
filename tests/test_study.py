"""benchmarks/study.py: which runs are still to do, with seeds landing out of order, and each branch of the verdict
rule (Welch's t-test over matched seeds), against scipy's own test."""

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BETTER, WORSE = "da_occ_tiny", "flashocc_tiny"  # the arms of the claim "DA-Occ beats FlashOcc at matched size"
#: Every object class at 5% IoU: a run that has learned objects.
SCORES = {name: 0.05 for name in ("car", "truck", "construction_vehicle", "bus", "trailer", "barrier", "motorcycle",
                                  "bicycle", "pedestrian", "traffic_cone")}  # fmt: skip


def _load_study():
    """benchmarks/study.py as a module (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("benchmarks_study", REPO / "benchmarks" / "study.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


STUDY = _load_study()
#: The budget of the claim "DA-Occ beats FlashOcc at matched size": 24 epochs of batch 4.
BUDGET = STUDY.RECIPE_BUDGET


@pytest.fixture(scope="module")
def study():
    return STUDY


def _args(out: Path) -> argparse.Namespace:
    world = out / "world"
    world.mkdir(exist_ok=True)
    (world / "labels.npz").write_bytes(b"\x00\x01")
    # The claim's budget only: da_occ_tiny also runs at the budget of the DAC claims.
    return argparse.Namespace(out=out, data=world, arms=[BETTER, WORSE], steps=[BUDGET.steps], batch_size=BUDGET.batch,
                              seeds=2, commit=False, jobs=1, doc=out / "results.md")  # fmt: skip


def _land(study, out: Path, arm: str, seed: int, miou: float, world: str | None = None, budget=BUDGET) -> None:
    """A finished run's result file, trained on the world of :func:`_args` unless ``world`` names another hash."""
    path = study.result_path(out, arm, budget, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    sha256 = world or study.world_digest(_args(out).data.resolve())
    result = {"arm": arm, "seed": seed, "steps": budget.steps, "batch_size": budget.batch, "miou": miou, "iou": 0.5,
              "rayiou": 0.1, "device": "CPU", "per_class_iou": SCORES, "train_seconds": 60.0,
              "train_cpu_seconds": 120.0, "eval_seconds": 1.0, "eval_cpu_seconds": 2.0,
              "world": {"sha256": sha256}}  # fmt: skip
    path.write_text(json.dumps(result))


def test_the_claims_budgets(study):
    claim = next(c for c in study.CLAIMS if (c.better, c.worse) == (BETTER, WORSE))
    assert claim.budget == BUDGET == study.Budget(1728, 4) and str(BUDGET) == "1728 steps of 4"
    assert BUDGET.folder == "1728-steps-of-4" and study.CAMERA_BUDGET.folder == "1500-steps"
    budgets = study.budgets()
    assert len(budgets) == len(set(budgets)) and [b for _, b in budgets] == sorted(b for _, b in budgets)
    assert (BETTER, study.CAMERA_BUDGET) in budgets and (BETTER, BUDGET) in budgets  # the DAC claims and this one
    assert (WORSE, study.CAMERA_BUDGET) not in budgets


def test_a_seed_that_landed_first_is_not_run_again(study, tmp_path):
    _land(study, tmp_path, BETTER, 1, 0.2)  # seed 1 finished before seed 0 (runs in parallel)
    # Seed-major, in the order of ARMS (flashocc_tiny first).
    assert study._todo(_args(tmp_path), set()) == [(WORSE, BUDGET, 0), (BETTER, BUDGET, 0), (WORSE, BUDGET, 1)]
    assert study._todo(_args(tmp_path), {(BETTER, BUDGET, 0), (WORSE, BUDGET, 0)}) == [(WORSE, BUDGET, 1)]
    args = _args(tmp_path)
    args.steps = None  # every budget: da_occ_tiny's runs for the DAC claims come first
    assert study._todo(args, set())[:2] == [(BETTER, study.CAMERA_BUDGET, 0), (WORSE, BUDGET, 0)]


def _runs(better: list[float], worse: list[float], budgets=(BUDGET, BUDGET)) -> dict[str, list[dict]]:
    def arm(values, budget):
        return [{"seed": seed, "steps": budget.steps, "batch_size": budget.batch, "miou": value, "iou": 0.5,
                 "per_class_iou": SCORES} for seed, value in enumerate(values)]  # fmt: skip

    return {BETTER: arm(better, budgets[0]), WORSE: arm(worse, budgets[1])}


@pytest.mark.parametrize(
    ("better", "worse", "status"),
    [
        ((0.20, 0.22, 0.21, 0.23, 0.20), (0.10, 0.12, 0.11, 0.10, 0.12), "holds"),
        ((0.10, 0.12, 0.11, 0.10, 0.12), (0.20, 0.22, 0.21, 0.23, 0.20), "reversed"),
        ((0.20, 0.25, 0.15, 0.22, 0.18), (0.19, 0.24, 0.16, 0.21, 0.17), "no effect detected"),
    ],
)
def test_verdicts_follow_welchs_test_as_scipy_computes_it(study, better, worse, status):
    from scipy import stats

    claim = next(c for c in study.CLAIMS if (c.better, c.worse) == (BETTER, WORSE))
    result = study.verdict(claim, _runs(better, worse))
    assert result["status"] == status and result["seeds"] == [0, 1, 2, 3, 4]
    independent = stats.ttest_ind([100 * v for v in better], [100 * v for v in worse], equal_var=False)
    assert result["p"] == pytest.approx(independent.pvalue, rel=1e-9)
    low, high = independent.confidence_interval(0.95)
    assert result["ci95"] == pytest.approx([low, high], rel=1e-9)
    assert result["difference"] == pytest.approx(100 * (sum(better) - sum(worse)) / 5)
    # The detectable difference: what these seeds find 4 times in 5 at p < 0.05; larger than the one not detected.
    if status == "no effect detected":
        assert result["detectable"] > abs(result["difference"])


def test_holms_adjustment(study):
    # Sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1: 0.02, 0.03, 0.06, then 0.04 lifted to the 0.06 before it.
    assert study.holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert study.holm([0.3, 0.6]) == [0.6, 0.6] and study.holm([0.01, 0.01]) == [0.02, 0.02]  # capped; ties alike
    assert study.holm([0.02]) == [0.02] and study.holm([]) == []


def test_a_claim_needs_two_matched_seeds_and_one_budget(study):
    claim = next(c for c in study.CLAIMS if (c.better, c.worse) == (BETTER, WORSE))
    runs = _runs([0.2, 0.3], [0.1])
    assert study.verdict(claim, runs)["status"] == "too few matched seeds (1)"
    runs[WORSE].append({"seed": 7, "steps": 1728, "batch_size": 4, "miou": 0.1, "iou": 0.5})  # only one arm's seed
    assert study.verdict(claim, runs)["status"] == "too few matched seeds (1)"
    # Runs at another budget (here 1728 steps of batch 1) are not this claim's.
    other = study.Budget(BUDGET.steps)
    result = study.verdict(claim, _runs([0.2, 0.3], [0.1, 0.2], (BUDGET, other)))
    assert result["status"] == "not run at 1728 steps of 4"
    assert study.verdict(claim, {BETTER: [], WORSE: []})["status"] == "not run at 1728 steps of 4"
    assert study.verdict(claim, _runs([0.2, 0.3], [0.1, 0.2]))["objects"] == pytest.approx(5.0)


def test_a_run_on_another_copy_of_the_world_is_run_again(study, tmp_path):
    _land(study, tmp_path, BETTER, 0, 0.2)
    _land(study, tmp_path, WORSE, 0, 0.1, world="sha256:another")
    _land(study, tmp_path, BETTER, 1, 0.2)
    study.result_path(tmp_path, WORSE, BUDGET, 1).write_text(json.dumps({"seed": 1, "miou": 0.1}))  # no hash
    assert study._todo(_args(tmp_path), set()) == [(WORSE, BUDGET, 0), (WORSE, BUDGET, 1)]


def test_every_arm_runs_the_same_seeds(study, tmp_path):
    for seed, miou in enumerate((0.20, 0.22)):
        _land(study, tmp_path, BETTER, seed, miou)
    args = _args(tmp_path)
    args.seeds = 3
    assert study._todo(args, set()) == [(WORSE, BUDGET, 0), (WORSE, BUDGET, 1), (WORSE, BUDGET, 2), (BETTER, BUDGET, 2)]


def test_run_all_runs_what_is_missing_and_rewrites_the_summary(study, tmp_path, monkeypatch):
    ran = []

    def fake_run(name, budget, seed, args):
        ran.append((name, budget, seed))
        _land(study, args.out, name, seed, 0.2 if name == BETTER else 0.1, budget=budget)

    monkeypatch.setattr(study, "run_arm", fake_run)
    _land(study, tmp_path, WORSE, 0, 0.1)
    doc = tmp_path / "results.md"  # a document with a marked table: rewritten with the summary
    doc.write_text("# Results\n\nprose\n<!-- study.py: claims -->\nSTALE\n<!-- end -->\nmore prose\n")
    study.run_all(_args(tmp_path))
    text = doc.read_text()
    assert text.startswith("# Results\n\nprose\n<!-- study.py: claims -->\n| paper |") and "STALE" not in text
    assert text.endswith("<!-- end -->\nmore prose\n") and "DA-Occ beats FlashOcc at matched size" in text
    assert ran == [(BETTER, BUDGET, 0), (WORSE, BUDGET, 1), (BETTER, BUDGET, 1)]
    summary = json.loads((tmp_path / "study.json").read_text())
    assert json.dumps(summary).count("holds") >= 1


def test_a_claim_compares_runs_of_one_device_and_one_world_copy(study):
    claim = next(c for c in study.CLAIMS if (c.better, c.worse) == (BETTER, WORSE))
    runs = _runs([0.20, 0.22, 0.21, 0.30], [0.10, 0.12, 0.11, 0.40])
    for arm in runs.values():
        for run in arm:
            run["device"], run["world"] = "GPU", {"sha256": "sha256:aa"}
    runs[BETTER][3]["device"] = "CPU"  # seed 3 ran elsewhere for one arm: not matched
    result = study.verdict(claim, runs)
    assert result["seeds"] == [0, 1, 2] and (result["device"], result["world"]) == ("GPU", "sha256:aa")
    runs[WORSE][2]["world"] = {"sha256": "sha256:bb"}  # another copy of the world
    assert study.verdict(claim, runs)["seeds"] == [0, 1]
    runs[WORSE][1]["world"] = {}  # not recorded: a setting of its own
    assert study.verdict(claim, runs)["status"] == "too few matched seeds (1)"
    assert study._where(study.verdict(claim, _runs([0.2, 0.3], [0.1, 0.2]))) == "CPU, world not recorded"


def test_a_worlds_digest_is_its_content_wherever_it_lies(tmp_path):
    from occkit.outputs import folder_digest, write_manifest

    a, b = tmp_path / "a", tmp_path / "b"
    for folder in (a, b):
        (folder / "gts").mkdir(parents=True)
        (folder / "gts" / "labels.npz").write_bytes(b"\x00\x01")
        (folder / "splits.json").write_text("{}")
        write_manifest(folder, "occkit sim")
    (b / ".occkit").mkdir()
    (b / ".occkit" / "index.npz").write_bytes(b"a cache")  # readers' cache: not content
    assert folder_digest(a) == folder_digest(b)
    (b / "gts" / "labels.npz").write_bytes(b"\x00\x02")
    assert folder_digest(a) != folder_digest(b)
    (b / "gts" / "labels.npz").unlink()
    with pytest.raises(FileNotFoundError, match="labels.npz"):
        folder_digest(b)


def test_the_committed_verdicts_recompute_from_their_seed_files(study):
    """docs/results/study/study.json against its per-seed files, with scipy's Welch test rather than the study's:
    each claim's seeds ran on its device and world copy for both arms, no other setting matches more seeds, and the
    difference, interval, p-value and verdict come out the same."""
    from scipy import stats

    folder = REPO / "docs" / "results" / "study"
    summary = json.loads((folder / "study.json").read_text())

    def setting(run):
        return run.get("device", "CPU"), (run.get("world") or {}).get("sha256")

    finished = study._finished(folder)  # the seed files, read as the study reads them

    def runs_of(arm, budget):
        runs = [run for run in finished[arm] if study.Budget.of(run) == study.Budget(**budget)]
        return {(setting(run), run["seed"]): run for run in runs}

    tested = 0
    for claim in summary["claims"]:
        if "difference" not in claim:
            continue
        better, worse = runs_of(claim["better"], claim["budget"]), runs_of(claim["worse"], claim["budget"])
        where = (claim["device"], claim["world"])
        matched = {}
        for key in better.keys() & worse.keys():
            matched.setdefault(key[0], []).append(key[1])
        assert sorted(matched[where]) == claim["seeds"], claim["text"]
        assert all(len(seeds) <= len(claim["seeds"]) for seeds in matched.values()), claim["text"]
        a = [100 * better[(where, s)]["miou"] for s in claim["seeds"]]
        b = [100 * worse[(where, s)]["miou"] for s in claim["seeds"]]
        test = stats.ttest_ind(a, b, equal_var=False)
        assert claim["p"] == pytest.approx(test.pvalue, rel=1e-9, abs=1e-12), claim["text"]
        assert claim["ci95"] == pytest.approx(list(test.confidence_interval(0.95)), rel=1e-9), claim["text"]
        assert claim["difference"] == pytest.approx(sum(a) / len(a) - sum(b) / len(b)), claim["text"]
        expected = ("holds" if test.statistic > 0 else "reversed") if test.pvalue < 0.05 else "no effect detected"
        assert claim["status"] == expected, claim["text"]
        tested += 1
    assert tested >= 1
    # Holm's adjustment over the claims tested: each p times the number of claims at or below it in rank, never
    # below a smaller p's adjusted value.
    ranked = sorted(claim["p"] for claim in summary["claims"] if "p" in claim)
    for claim in (c for c in summary["claims"] if "p" in c):
        expected = max(min(1.0, (len(ranked) - k) * q) for k, q in enumerate(ranked) if q <= claim["p"])
        assert claim["p_holm"] == pytest.approx(expected, rel=1e-12), claim["text"]


def test_the_runs_picked_by_arms_and_budgets(study):
    daocc = [pair for pair in study.budgets() if pair[1] == study.DAOCC_BUDGET]
    assert study._pairs(None, [500]) == daocc and len(daocc) == 5
    assert study._pairs([BETTER], None) == [(BETTER, study.CAMERA_BUDGET), (BETTER, BUDGET)]
    assert study._pairs(None, None) == study.budgets()
    # Both: those arms at those budgets, a claim's or not (where an arm stands at another budget).
    assert study._pairs([BETTER, WORSE], [3000]) == [(WORSE, study.Budget(3000)), (BETTER, study.Budget(3000))]
    assert study._pairs([WORSE], [72], batch=4) == [(WORSE, study.Budget(72, 4))]
    assert study._objects(0.5) == "0.50 (ground only)" and study._objects(4.0) == "4.00"


def test_the_documents_study_tables_are_the_result_files(study):
    """docs/results.md's marked tables are what the committed result files give (no number without its file)."""
    doc = (REPO / "docs" / "results.md").read_text()
    _, tables = study.build_report(REPO / "docs" / "results" / "study", Path("data/study-world"))
    assert all(f"<!-- study.py: {name} -->" in doc for name in tables)
    assert study.fill_tables(doc, tables) == doc
