"""The papers' ablations at tiny scale: every arm trained with one budget on one synthetic world, over seeds.

    python benchmarks/study.py [--data data/study-world] [--steps N ...] [--batch-size B] [--seeds 5]
        [--arms NAME ...] [--out docs/results/study] [--runs runs/study] [--doc docs/results.md] [--commit] [--report]

Each arm is a CPU-sized zoo entry with one mechanism changed (:data:`ARMS`); a run trains it for a budget of
optimizer steps of some batch size from its zoo recipe, with seeds 0, 1, ... (the seed sets the initial weights, the
sample order and the augmentation draws), on the training scenes of one world (:data:`WORLD`, written first if
absent), and scores it on the world's held-out scenes: mIoU, the object classes' mIoU and geometry IoU under the camera
mask, and RayIoU (temporal models streamed scene by scene, as ``occkit eval`` runs them).

Each paper claim is a comparison of two arms at one budget (:data:`CLAIMS`; the budgets and why each is what it is:
:data:`DAOCC_BUDGET`, :data:`CAMERA_BUDGET`, :data:`RECIPE_BUDGET`), on the seeds both arms ran on one device and one
copy of the world (matched: the same seed set for both; each run records its device and its world's content hash),
every arm ``--seeds`` of them. Its verdict (:func:`verdict`) is a Welch test of the arms' mIoU over those seeds: the
mean difference with its 95% confidence interval and the two-sided p-value; "holds" or "reversed" where p < 0.05 in
that direction, else "no effect detected", with the smallest difference these seeds would have detected (at 80%
power). The runs to do are every (arm, budget) a claim needs, times the seeds; ``--arms`` or ``--steps`` picks some
of them, and both together run those arms for those steps of ``--batch-size`` (to see where an arm stands at a
budget no claim uses).

Resumable: each finished run writes ``<out>/<arm>/<budget>/seed-<k>.json`` (``<budget>``: ``1500-steps``,
``1728-steps-of-4``; with ``--commit``, committed to git at once with the summary, so an interrupted study keeps what
it finished). A rerun skips the runs finished on this world (its content hash); it runs again, and replaces, those of
another copy or none recorded; a killed run resumes from the newest checkpoint in ``<runs>/<arm>/<budget>/seed-<k>``.
The summary (``<out>/study.json``, ``<out>/study.md``, ``<out>/study.png`` and the marked tables of ``--doc``) is
rewritten after every run; ``--report`` only rewrites it. Times are wall-clock and CPU seconds of this process and its
data workers, per device: run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import multiprocessing
import os
import resource
import statistics
import subprocess
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

import torch

from occkit import zoo
from occkit.classes import DETECTION_CLASSES
from occkit.data.names import folder_name
from occkit.engine.evaluate import evaluation_dataset, load_trained, score_model
from occkit.engine.train import train
from occkit.experiment import Experiment, replace_train
from occkit.figure import new_figure, save_figure
from occkit.models.daocc import with_bev_extent
from occkit.models.temporal import TemporalConfig
from occkit.outputs import folder_digest
from occkit.sim.generate import SimConfig, simulate_dataset

#: 16 scenes of 24 key frames at 400 x 225: the sim holds the last 4 out (val), 12 train (288 frames).
WORLD = {"scenes": 16, "frames": 24, "image_size": (400, 225), "seed": 7}
#: The scores of a run, each in [0, 1].
METRICS = ("miou", "iou", "rayiou")


def _model(experiment: Experiment, **changes) -> Experiment:
    return dataclasses.replace(experiment, model=dataclasses.replace(experiment.model, **changes))


def _data(experiment: Experiment, **changes) -> Experiment:
    return dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, **changes))


def _concat_history(frames: int) -> Callable[[Experiment], Experiment]:
    """da_occ_tiny with BEVDet4D's concatenation of ``frames`` earlier key frames (as da_occ_1f)."""

    def change(experiment: Experiment) -> Experiment:
        temporal = TemporalConfig(fusion="concat", history=frames)
        m = experiment.model
        context = m.bev.in_channels
        experiment = _model(experiment, temporal=temporal,
                            bev=dataclasses.replace(m.bev, in_channels=temporal.out_channels(context)))  # fmt: skip
        return _data(experiment, history=frames)

    return change


@dataclass(frozen=True)
class Arm:
    """One arm: a zoo entry and a change to its experiment."""

    entry: str
    change: Callable[[Experiment], Experiment] | None
    description: str
    sampler: str | None = None
    """The training order, when not the entry's own (``streams``: the temporal control)."""

    def experiment(self) -> Experiment:
        experiment = zoo.experiment(self.entry)
        experiment = experiment if self.change is None else self.change(experiment)
        return experiment if self.sampler is None else replace_train(experiment, sampler=self.sampler)


#: Arm name -> arm. Names say what differs from the entry: ``-`` removes a mechanism, ``+`` adds one.
ARMS: dict[str, Arm] = {
    # DAOcc: detection assistance, the BEV range extension, and the sensors.
    "daocc_tiny": Arm("daocc_tiny", None, "camera + LiDAR fusion, detection head, BEV range +-43.2 m"),
    "daocc_tiny - detection": Arm(
        "daocc_tiny", lambda e: _data(_model(e, detection=None), boxes=False), "without the auxiliary detection head"
    ),
    "daocc_tiny - BVRE": Arm(
        "daocc_tiny", lambda e: dataclasses.replace(e, model=with_bev_extent(e.model, 40.8)),
        "BEV range +-40.8 m, just the Occ3D grid",
    ),
    "daocc_tiny camera only": Arm(
        "daocc_tiny", lambda e: _data(_model(e, lidar=None), sweeps=-1), "the camera branch alone (projection)"
    ),
    "daocc_tiny LiDAR only": Arm(
        "daocc_tiny", lambda e: _data(_model(e, image=None), cameras=()), "the LiDAR branch alone"
    ),
    # DA-Occ against FlashOcc, and DA-Occ's mechanisms one at a time.
    "flashocc_tiny": Arm("flashocc_tiny", None, "the baseline: LSS, BEV encoder, channel-to-height"),
    "da_occ_tiny": Arm("da_occ_tiny", None, "LSS with depth scores + height-score projection + DACs"),
    "da_occ_tiny - height": Arm(
        "da_occ_tiny", lambda e: _model(e, height_net=None), "without the height branch (FlashOcc + BEV DACs)"
    ),
    "da_occ_tiny - HeightNet DAC": Arm(
        "da_occ_tiny", lambda e: _model(e, height_net=dataclasses.replace(e.model.height_net, dac_blocks=0)),
        "HeightNet's DACs replaced by the 3x3 BasicBlocks they replaced",
    ),
    "da_occ_tiny - BEV horizontal DAC": Arm(
        "da_occ_tiny", lambda e: _model(e, bev_horizontal_dac=False), "without D_h on the BEV"
    ),
    "da_occ_tiny - BEV vertical DAC": Arm(
        "da_occ_tiny", lambda e: _model(e, bev_vertical_dac=False), "without D_v on the BEV"
    ),
    "da_occ_tiny - height-volume DAC": Arm(
        "da_occ_tiny", lambda e: _model(e, height_volume_dac=False), "without D_v along z on the height volume"
    ),
    # Single frame against temporal.
    "da_occ_tiny + 1 frame": Arm("da_occ_tiny", _concat_history(1), "one earlier key frame, concatenated (BEVDet4D)"),
    "da_occ_tiny + recurrent": Arm(
        "da_occ_tiny_temporal", None, "a recurrent BEV state over every earlier frame, trained on streams"
    ),
    "da_occ_tiny (streams)": Arm(
        "da_occ_tiny", None, "single frame, trained in the recurrent arm's order (the control)", sampler="streams"
    ),
}  # fmt: skip


@dataclass(frozen=True, order=True)
class Budget:
    """A run's length: ``steps`` optimizer steps of ``batch`` samples (the study world's 288 training frames are an
    epoch)."""

    steps: int
    batch: int = 1

    def __str__(self) -> str:
        return f"{self.steps} steps" + (f" of {self.batch}" if self.batch > 1 else "")

    @property
    def folder(self) -> str:
        """Its runs' folder name: ``1500-steps``, ``1728-steps-of-4``."""
        return f"{self.steps}-steps" + (f"-of-{self.batch}" if self.batch > 1 else "")

    @staticmethod
    def of(run: dict) -> Budget:
        """The budget a finished run trained with (runs without ``batch_size`` trained at batch 1)."""
        return Budget(run["steps"], run.get("batch_size", 1))


#: The claims' budgets, each long enough for the claim's arms to predict objects, not only the ground: their object
#: mIoU (the mean IoU of nuScenes' ten object classes, a column of the report) is then well above zero.
#: DAOcc's arms with LiDAR predict objects within a few hundred steps (object mIoU 10.8 to 16.6 in each run at 500);
#: its camera branch alone does not (0.0), which is the gap "fusion beats camera only" measures at this budget.
DAOCC_BUDGET = Budget(500)
#: DA-Occ's direction-aware convolutions and one history frame: each arm with the height branch predicts objects by
#: 1,500 steps of batch 1 (object mIoU 3.9 to 5.6 in each run of these arms at that budget).
CAMERA_BUDGET = Budget(1500)
#: 24 epochs of batch 4, FlashOcc's and DA-Occ's own schedule length, for the claims with an arm that at 1,500 steps of
#: batch 1 predicts little beyond the ground: FlashOcc (object mIoU 0.06 and 0.13; 0.03 at 3,000 steps), DA-Occ
#: without its height branch (0.58, 0.55) and the recurrent history (2.61, 0.55; its control, trained in the same
#: order: 1.79, 2.23). On a world of the same size (16 scenes of 24 frames, seed 2026), flashocc_tiny trained 24
#: epochs of batch 4 ends at 3.4 object mIoU, and da_occ_tiny at 8.4 (docs/results/shipped/*_24_epochs/val.jsonl).
RECIPE_BUDGET = Budget(1728, 4)
#: The object mIoU (points) below which a run counts as predicting only the ground: the report marks a claim whose
#: runs fall below it (at 1,500 steps flashocc_tiny scored 0.06 and 0.13, the arms with the height branch 3.9 to 5.6).
OBJECTS_LEARNED = 1.0


@dataclass(frozen=True)
class Claim:
    """A paper's claim as a comparison at one budget: ``better`` should score above ``worse`` after ``budget``."""

    paper: str
    text: str
    better: str
    worse: str
    budget: Budget
    paper_gain: str
    """What the paper measures for it (mIoU on Occ3D-nuScenes), "-" where it does not."""


CLAIMS: list[Claim] = [
    Claim("DAOcc", "the auxiliary detection head improves occupancy", "daocc_tiny", "daocc_tiny - detection",
          DAOCC_BUDGET, "+1.56"),
    Claim("DAOcc", "the BEV range extension (BVRE) improves occupancy", "daocc_tiny", "daocc_tiny - BVRE",
          DAOCC_BUDGET, "+0.5"),
    Claim("survey", "fusion beats camera only", "daocc_tiny", "daocc_tiny camera only", DAOCC_BUDGET, "-"),
    Claim("survey", "fusion beats LiDAR only", "daocc_tiny", "daocc_tiny LiDAR only", DAOCC_BUDGET, "-"),
    Claim("DA-Occ", "DA-Occ beats FlashOcc at matched size", "da_occ_tiny", "flashocc_tiny", RECIPE_BUDGET,
          "+2.43 (34.38 against M0's 31.95)"),
    Claim("DA-Occ", "the height branch helps", "da_occ_tiny", "da_occ_tiny - height", RECIPE_BUDGET,
          "not ablated; 16 height bins against 4: +1.5"),
    Claim("DA-Occ", "HeightNet's DACs help", "da_occ_tiny", "da_occ_tiny - HeightNet DAC", CAMERA_BUDGET,
          "all four DACs: +1.8"),
    Claim("DA-Occ", "the horizontal BEV DAC helps", "da_occ_tiny", "da_occ_tiny - BEV horizontal DAC", CAMERA_BUDGET,
          "(all four: +1.8)"),
    Claim("DA-Occ", "the vertical BEV DAC helps", "da_occ_tiny", "da_occ_tiny - BEV vertical DAC", CAMERA_BUDGET,
          "(all four: +1.8)"),
    Claim("DA-Occ", "the height volume's DAC helps", "da_occ_tiny", "da_occ_tiny - height-volume DAC", CAMERA_BUDGET,
          "(all four: +1.8)"),
    Claim("DA-Occ", "one history frame helps", "da_occ_tiny + 1 frame", "da_occ_tiny", CAMERA_BUDGET,
          "+1.39 (35.77 against 34.38)"),
    Claim("DA-Occ", "a long history helps", "da_occ_tiny + recurrent", "da_occ_tiny", RECIPE_BUDGET,
          "+4.9 (16 frames: 39.3)"),
    Claim("DA-Occ", "a long history helps, order held equal", "da_occ_tiny + recurrent", "da_occ_tiny (streams)",
          RECIPE_BUDGET, "-"),
]  # fmt: skip


def _run_order(pair: tuple[str, Budget]) -> tuple[Budget, int]:
    """Sort key of (arm, budget) pairs: by budget, then in :data:`ARMS`' order."""
    return pair[1], list(ARMS).index(pair[0])


def budgets() -> list[tuple[str, Budget]]:
    """Every (arm, budget) a claim needs, by budget, then in :data:`ARMS`' order."""
    needed = {(arm, claim.budget) for claim in CLAIMS for arm in (claim.better, claim.worse)}
    return sorted(needed, key=_run_order)


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (the data loader's workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _device_name() -> str:
    """What trained the run: the GPU's name, or the CPU's core count."""
    if torch.cuda.is_available():
        return torch.cuda.get_device_name()
    return f"CPU ({os.cpu_count()} cores)"


@functools.cache
def world_digest(data: Path) -> str:
    """The content hash of the world at ``data`` (:func:`occkit.outputs.folder_digest`), once per process."""
    return folder_digest(data)


def finished_run(result_file: Path, data: Path) -> dict | None:
    """The run stored in ``result_file`` if it trained on the world at ``data`` (the same content hash), else None:
    a run that recorded no hash, or another world's, cannot be matched with this world's runs, and is run again."""
    if not result_file.is_file():
        return None
    run = json.loads(result_file.read_text())
    return run if run.get("world", {}).get("sha256") == world_digest(data.resolve()) else None


def run_folder(root: Path, name: str, budget: Budget, seed: int) -> Path:
    """Where one run of arm ``name`` at ``budget`` lives under ``root``: its result file's folder under ``--out``, its
    checkpoints under ``--runs``."""
    return root / folder_name(name) / budget.folder / f"seed-{seed}"


def result_path(out: Path, name: str, budget: Budget, seed: int) -> Path:
    """The result file of one run: ``<out>/<arm>/<steps>-steps[-of-<batch>]/seed-<k>.json``."""
    return run_folder(out, name, budget, seed).with_suffix(".json")


def run_arm(name: str, budget: Budget, seed: int, args: argparse.Namespace, threads: int | None = None) -> dict:
    """Train and score one arm for ``budget`` at one seed, on ``threads`` CPU threads (the process's count when
    None); the stored result when it already ran on this world."""
    result_file = result_path(args.out, name, budget, seed)
    if (run := finished_run(result_file, args.data)) is not None:
        return run
    if result_file.is_file():
        print(
            f"[study] {name}, {budget}, seed {seed}: {result_file} trained on another copy of the world (or "
            "did not record it): running it again on this one",
            flush=True,
        )
    arm = ARMS[name]
    experiment = _data(arm.experiment(), root=str(args.data))
    experiment = replace_train(experiment, max_steps=budget.steps, batch_size=budget.batch, epochs=10_000,
                               val_every=-1, checkpoint_every=args.checkpoint_every, seed=seed)  # fmt: skip
    folder = run_folder(args.runs, name, budget, seed)
    print(f"[study] {name}, seed {seed}: training {budget} into {folder}", flush=True)
    pointer = folder / "last.json"  # the checkpoint a resumed run starts from
    start_step = int(json.loads(pointer.read_text())["step"]) if pointer.is_file() else 0
    # Set for each run, and the count it trained with recorded: a pool's worker trains one run after another.
    if threads is not None:
        torch.set_num_threads(threads)
    train_threads = torch.get_num_threads()
    wall, cpu = time.perf_counter(), _cpu_seconds()
    run = train(experiment, folder, resume="auto", progress=args.progress)
    train_wall, train_cpu = time.perf_counter() - wall, _cpu_seconds() - cpu
    if 0 < start_step < run.steps:
        # Resumed (an earlier process trained the first steps and was stopped): the times of the steps this process
        # took, scaled to the whole run (`resumed_from_step` in the result says so).
        scale = run.steps / (run.steps - start_step)
        train_wall, train_cpu = train_wall * scale, train_cpu * scale
    # Scored where it trained (train() picks CUDA when there is one).
    device = "cuda" if torch.cuda.is_available() else "cpu"
    model, experiment = load_trained(sorted(folder.glob("step-*.pt"))[-1], device=device)
    dataset = evaluation_dataset(experiment, args.data, "val")
    torch.set_flush_denormal(True)
    wall, cpu = time.perf_counter(), _cpu_seconds()
    scores = score_model(model, dataset, workers=1)
    result = {
        "arm": name, "entry": arm.entry, "description": arm.description, "seed": seed, "steps": run.steps,
        "batch_size": budget.batch,
        **{key: scores[key] for key in METRICS}, "per_class_iou": scores["per_class_iou"], "frames": scores["frames"],
        "train_seconds": train_wall, "train_cpu_seconds": train_cpu, "resumed_from_step": start_step,
        "eval_seconds": time.perf_counter() - wall,
        "eval_cpu_seconds": _cpu_seconds() - cpu, "params": sum(p.numel() for p in model.parameters()),
        "threads": train_threads, "device": _device_name(),
        "world": {**WORLD, "data": str(args.data), "sha256": world_digest(args.data.resolve())},
    }  # fmt: skip
    result_file.parent.mkdir(parents=True, exist_ok=True)
    result_file.write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"[study] {name}, {budget}, seed {seed}: mIoU {100 * result['miou']:.2f}, "
        f"IoU {100 * result['iou']:.2f}, RayIoU {100 * result['rayiou']:.2f} ({train_wall / 60:.1f} min training)",
        flush=True,
    )
    return result


def commit(name: str, budget: Budget, seed: int, out: Path, doc: Path | None) -> None:
    """Commit one finished run's result file with the summary it was just written into (and ``doc``'s tables)."""
    summary = [str(out / f"study.{ext}") for ext in ("json", "md", "png")] + ([str(doc)] if doc else [])
    files = [str(result_path(out, name, budget, seed)), *summary]
    # Another git command in the same checkout (its index lock) may make one try fail: try again before giving up.
    message = f"study: {name}, {budget}, seed {seed}"
    for attempt in range(5):
        added = subprocess.run(["git", "add", "--", *files]).returncode == 0
        if added and subprocess.run(["git", "commit", "-q", "-m", message, "--", *files]).returncode == 0:
            return
        time.sleep(2.0 * (attempt + 1))
    raise RuntimeError(f"could not commit {files[0]} (git add or commit failed five times); it stays on disk")


def _finished(out: Path) -> dict[str, list[dict]]:
    """Arm -> its finished runs, by budget, then seed."""
    runs = {}
    for name in ARMS:
        files = (out / folder_name(name)).glob("*-steps*/seed-*.json")
        found = [json.loads(f.read_text()) for f in files]
        runs[name] = sorted(found, key=lambda run: (Budget.of(run), run["seed"]))
    return runs


def object_miou(run: dict) -> float:
    """The mean IoU of nuScenes' ten object classes in a run's scores, in [0, 1]: near 0 while a model predicts
    only the ground and the background."""
    return statistics.mean(run["per_class_iou"][name] for name in DETECTION_CLASSES)


def summarise(runs: list[dict]) -> dict:
    """Mean, standard deviation (0 for one run), minimum and maximum of each metric over the seeds of one arm at
    one budget."""
    summary = {
        "seeds": [r["seed"] for r in runs],
        "devices": sorted({r.get("device", "CPU") for r in runs}),
        "train_minutes": statistics.mean(r["train_seconds"] for r in runs) / 60,
        "train_cpu_minutes": statistics.mean(r["train_cpu_seconds"] for r in runs) / 60,
    }
    for key in (*METRICS, "object_miou"):
        values = [object_miou(r) if key == "object_miou" else r[key] for r in runs]
        summary[key] = {"mean": statistics.mean(values), "std": statistics.stdev(values) if len(values) > 1 else 0.0,
                        "min": min(values), "max": max(values)}  # fmt: skip
    return summary


#: Significance level of a verdict, and the power the detectable effect is stated at.
ALPHA, POWER = 0.05, 0.8


def welch(a: list[float], b: list[float]) -> dict[str, float]:
    """Welch's unequal-variance t-test of ``mean(a) - mean(b)``: the difference, its 95% confidence interval, the
    two-sided p-value, the degrees of freedom (Welch-Satterthwaite) and the smallest difference the test detects with
    :data:`POWER` at :data:`ALPHA` (``(t_{1 - alpha / 2} + t_{power}) x standard error``). Needs two values per side."""
    from scipy import stats

    if len(a) < 2 or len(b) < 2:
        raise ValueError(f"Welch's test needs at least two values per arm, got {len(a)} and {len(b)}")
    va, vb = statistics.variance(a) / len(a), statistics.variance(b) / len(b)
    difference, error = statistics.mean(a) - statistics.mean(b), (va + vb) ** 0.5
    if error == 0:  # identical values within each arm: the difference is exact
        p = 0.0 if difference else 1.0
        return {"difference": difference, "ci95": [difference, difference], "p": p, "df": float("inf"),
                "detectable": 0.0}  # fmt: skip
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    t = difference / error
    critical = stats.t.ppf(1 - ALPHA / 2, df)
    return {"difference": difference, "ci95": [difference - critical * error, difference + critical * error],
            "p": float(2 * stats.t.sf(abs(t), df)), "df": df,
            "detectable": float((critical + stats.t.ppf(POWER, df)) * error)}  # fmt: skip


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of ``p_values`` for testing them together: the k-th smallest is multiplied by
    ``m - k + 1`` (``m`` tests), capped at 1 and never below the adjusted value before it, so that comparing each
    adjusted value with :data:`ALPHA` keeps the chance of any false "holds" among the ``m`` below ALPHA."""
    adjusted, running = [0.0] * len(p_values), 0.0
    for rank, index in enumerate(sorted(range(len(p_values)), key=p_values.__getitem__)):
        running = max(running, min(1.0, (len(p_values) - rank) * p_values[index]))
        adjusted[index] = running
    return adjusted


def _setting(run: dict) -> tuple[str, str | None]:
    """Where a run trained: its device and its world's content hash (None where the run did not record it)."""
    return run.get("device", "CPU"), (run.get("world") or {}).get("sha256")


def matched_seeds(better: list[dict], worse: list[dict]) -> tuple[tuple[str, str | None] | None, list[int]]:
    """The seeds both arms ran on one device and one copy of the world, and that (device, world hash): of the
    settings the arms share, the one with the most such seeds (None and no seeds when they share none)."""
    by_setting: dict[tuple[str, str | None], list[set[int]]] = {}
    for side, runs in enumerate((better, worse)):
        for run in runs:
            by_setting.setdefault(_setting(run), [set(), set()])[side].add(run["seed"])
    shared = {setting: sorted(a & b) for setting, (a, b) in by_setting.items() if a & b}
    if not shared:
        return None, []
    setting = max(sorted(shared, key=str), key=lambda s: len(shared[s]))
    return setting, shared[setting]


def verdict(claim: Claim, runs: dict[str, list[dict]]) -> dict:
    """A claim's verdict from its arms' runs on their matched seeds (:func:`matched_seeds`: the same seeds, one
    device, one copy of the world): the mIoU difference (better - worse, points), its 95% interval, the p-value,
    and "holds" / "reversed" (p < :data:`ALPHA` in that direction) or "no effect detected" with the smallest
    difference the seeds would have detected; ``objects``: the lowest object mIoU (points) of the runs compared,
    which says whether both arms had learned objects at this budget."""
    better, worse = (
        [r for r in runs.get(name) or [] if Budget.of(r) == claim.budget] for name in (claim.better, claim.worse)
    )
    if not better or not worse:
        return {"status": f"not run at {claim.budget}"}
    setting, seeds = matched_seeds(better, worse)
    where = {} if setting is None else {"device": setting[0], "world": setting[1]}
    if len(seeds) < 2:
        return {"status": f"too few matched seeds ({len(seeds)})", "seeds": seeds, **where}
    by_seed = [{r["seed"]: r for r in arm if _setting(r) == setting} for arm in (better, worse)]
    test = welch([100 * by_seed[0][s]["miou"] for s in seeds], [100 * by_seed[1][s]["miou"] for s in seeds])
    iou = statistics.mean(100 * (by_seed[0][s]["iou"] - by_seed[1][s]["iou"]) for s in seeds)
    objects = min(100 * object_miou(arm[s]) for arm in by_seed for s in seeds)
    direction = "holds" if test["difference"] > 0 else "reversed"
    status = direction if test["p"] < ALPHA else "no effect detected"
    return {"status": status, "seeds": seeds, **where, "difference": test["difference"], "ci95": test["ci95"],
            "p": test["p"], "df": test["df"], "detectable": test["detectable"], "iou_difference": iou,
            "objects": objects}  # fmt: skip


def _where(verdict: dict) -> str:
    """A claim's device and world copy as the report shows them: ``CPU (2 cores), world 1a2b3c4d``."""
    if "device" not in verdict:
        return "-"
    world = verdict["world"]
    return f"{verdict['device']}, " + (f"world {world.removeprefix('sha256:')[:8]}" if world else "world not recorded")


def _objects(lowest: float) -> str:
    """A claim's lowest object mIoU as the report shows it, marked where an arm predicts only the ground."""
    return f"{lowest:.2f}" + (" (ground only)" if lowest < OBJECTS_LEARNED else "")


def _p(p: float) -> str:
    """A p-value as the report shows it: three decimals, ``< 0.001`` below what they can show."""
    return "< 0.001" if p < 0.0005 else f"{p:.3f}"


def _cell(summary: dict, key: str) -> str:
    value = summary[key]
    return f"{100 * value['mean']:.2f} ± {100 * value['std']:.2f}"


def arms_table(summaries: list[dict]) -> list[str]:
    """The markdown table of every arm at every budget it ran: mean ± standard deviation over its seeds (%)."""
    lines = [
        "| arm | what differs | budget | trained on | seeds | mIoU | objects | IoU | RayIoU | train min | "
        "train CPU min |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for summary in summaries:
        lines.append(f"| `{summary['arm']}` | {ARMS[summary['arm']].description} | {summary['budget']} | "
                     f"{', '.join(summary['devices'])} | {len(summary['seeds'])} | {_cell(summary, 'miou')} | "
                     f"{_cell(summary, 'object_miou')} | {_cell(summary, 'iou')} | {_cell(summary, 'rayiou')} | "
                     f"{summary['train_minutes']:.1f} | {summary['train_cpu_minutes']:.1f} |")  # fmt: skip
    return lines


def claims_table(verdicts: list[dict]) -> list[str]:
    """The markdown table of the claims' verdicts (:func:`verdict`), beside the papers' own gains."""
    lines = ["| paper | claim | paper's gain (mIoU) | better | worse | budget | seeds | run on | "
             "mIoU difference (95% interval) | p | p (Holm) | IoU difference | objects | verdict | detectable |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for v in verdicts:
        head = (f"| {v['paper']} | {v['text']} | {v['paper_gain']} | `{v['better']}` | `{v['worse']}` | "
                f"{Budget(**v['budget'])} | ")  # fmt: skip
        if "difference" not in v:
            lines.append(f"{head}{len(v.get('seeds', []))} | {_where(v)} | - | - | - | - | - | {v['status']} | - |")
            continue
        low, high = v["ci95"]
        status = f"**{v['status']}**" if v["status"] in ("holds", "reversed") else v["status"]
        detectable = f"{v['detectable']:.2f}" if v["status"] == "no effect detected" else "-"
        lines.append(f"{head}{len(v['seeds'])} | {_where(v)} | {v['difference']:+.2f} ({low:+.2f} to {high:+.2f}) | "
                     f"{_p(v['p'])} | {_p(v['p_holm'])} | {v['iou_difference']:+.2f} | {_objects(v['objects'])} | "
                     f"{status} | {detectable} |")  # fmt: skip
    return lines


def hours_lines(hours: dict[str, dict[str, float]]) -> list[str]:
    """One line per device: its runs and their wall-clock and CPU hours."""
    return [f"- {device}: {spent['runs']} runs, {spent['wall_hours']:.2f} h wall-clock (the sum of the runs' own, "
            f"which overlap when runs shared the machine), {spent['cpu_hours']:.2f} CPU hours (each run's process "
            "and its data workers, training and scoring)." for device, spent in hours.items()]  # fmt: skip


#: What the claims table says of its columns, in study.md and docs/results.md.
CLAIMS_LEGEND = (
    "Each claim compares its two arms at its budget, on the seeds both ran on one device and one copy of the world "
    "(its content hash; older runs did not record it). The difference is the better arm's mean mIoU minus the worse "
    "arm's, with the range that holds the true difference 95 times in 100 (Welch's t-test, which allows the arms "
    "different spreads); a claim holds, or is reversed, only where a difference that large would arise by chance "
    "less than 5 times in 100 (p < 0.05). Otherwise no effect was detected, and the last column says how large a "
    "difference these seeds would have caught (4 times in 5). Objects: the lowest object mIoU of the runs compared; "
    f'"ground only" below {OBJECTS_LEARNED:.1f}, where an arm has learned little beyond the ground.'
)


def fill_tables(text: str, tables: dict[str, list[str]]) -> str:
    """``text`` with the lines between each ``<!-- study.py: NAME -->`` marker and the next ``<!-- end -->``
    replaced by ``tables[NAME]``; names without a marker are left out."""
    for name, lines in tables.items():
        begin = f"<!-- study.py: {name} -->\n"
        if begin not in text:
            continue
        start = text.index(begin) + len(begin)
        end = text.index("<!-- end -->", start)
        text = text[:start] + "\n".join(lines) + "\n" + text[end:]
    return text


def build_report(out: Path, data: Path) -> tuple[dict, dict[str, list[str]]]:
    """The summary of every finished run in ``out`` (trained on the world at ``data``) and its markdown tables."""
    runs = _finished(out)
    summaries = []  # one per arm and budget
    for name, arm_runs in runs.items():
        for budget in sorted({Budget.of(r) for r in arm_runs}):
            done = [r for r in arm_runs if Budget.of(r) == budget]
            summaries.append({"arm": name, "budget": str(budget), **summarise(done)})
    verdicts = [{**dataclasses.asdict(claim), **verdict(claim, runs)} for claim in CLAIMS]
    tested = [v for v in verdicts if "p" in v]
    for v, adjusted in zip(tested, holm([v["p"] for v in tested]), strict=True):
        v["p_holm"] = adjusted  # corrected for the number of claims tested so far
    hours: dict[str, dict[str, float]] = {}  # device -> wall-clock and CPU hours of its runs (training + scoring)
    for run in (r for arm_runs in runs.values() for r in arm_runs):
        device = hours.setdefault(run.get("device", "CPU"), {"runs": 0, "wall_hours": 0.0, "cpu_hours": 0.0})
        device["runs"] += 1
        device["wall_hours"] += (run["train_seconds"] + run["eval_seconds"]) / 3600
        device["cpu_hours"] += (run["train_cpu_seconds"] + run["eval_cpu_seconds"]) / 3600
    report = {"world": {**WORLD, "data": str(data)}, "arms": summaries, "claims": verdicts, "runs": runs,
              "hours": hours}  # fmt: skip
    return report, {"arms": arms_table(summaries), "claims": claims_table(verdicts), "hours": hours_lines(hours)}


def write_report(out: Path, args: argparse.Namespace) -> dict:
    """``study.json``, ``study.md`` and ``study.png`` from every finished run in ``out``, and the tables of
    ``args.doc`` (docs/results.md) between their markers (:func:`fill_tables`)."""
    report, tables = build_report(out, args.data)
    (out / "study.json").write_text(json.dumps(report, indent=2) + "\n")
    lines = [
        f"Every arm at each budget it ran (steps of batch 1 unless said) on the training scenes of `{args.data}`, "
        "scored on its held-out scenes; mean ± standard deviation over seeds (%). Objects: the mean IoU of the ten "
        "object classes (near 0 while a model predicts only the ground).",
        "",
        *tables["arms"],
        "",
        CLAIMS_LEGEND,
        "",
        *tables["claims"],
        "",
        *tables["hours"],
    ]
    (out / "study.md").write_text("\n".join(lines) + "\n")
    _plot(report["arms"], out / "study.png")
    if args.doc is not None and args.doc.is_file():
        args.doc.write_text(fill_tables(args.doc.read_text(), tables))
    return report


def _plot(summaries: list[dict], path: Path) -> None:
    """mIoU and IoU per arm and budget, mean with the seeds' minimum-maximum range as the error bar."""
    if not summaries:
        return
    fig = new_figure(11.0, 0.32 * len(summaries) + 1.4)
    axes = fig.subplots(1, 2, sharey=True)
    families = ["daocc", "flashocc", "da_occ"]
    colours = [f"C{families.index(ARMS[s['arm']].entry.split('_tiny')[0])}" for s in summaries]
    for axis, key, title in ((axes[0], "miou", "mIoU (%)"), (axes[1], "iou", "IoU (%)")):
        means = [100 * s[key]["mean"] for s in summaries]
        low = [m - 100 * s[key]["min"] for m, s in zip(means, summaries, strict=True)]
        high = [100 * s[key]["max"] - m for m, s in zip(means, summaries, strict=True)]
        axis.barh(range(len(summaries)), means, xerr=[low, high], color=colours, capsize=2)
        axis.set_title(title, fontsize=10)
        axis.grid(axis="x", alpha=0.3)
    labels = [f"{s['arm']} ({s['budget']})" for s in summaries]
    axes[0].set_yticks(range(len(summaries)), labels, fontsize=8)
    axes[0].invert_yaxis()
    fig.suptitle("tiny-scale ablations, held-out scenes (bars: mean; whiskers: range over seeds)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


#: One run of the study: arm, budget, seed.
Job = tuple[str, Budget, int]


def _pairs(arms: list[str] | None, steps: list[int] | None, batch: int = 1) -> list[tuple[str, Budget]]:
    """The (arm, budget) pairs to run: the claims' (:func:`budgets`) of ``arms`` at ``steps`` (None: all); when both
    are given, every arm for every number of steps of ``batch``, whether or not a claim compares it there (to see
    where an arm stands at another budget)."""
    if arms and steps:
        pairs = ((a, Budget(s, batch)) for a in arms for s in steps)
        return sorted(pairs, key=_run_order)
    return [(a, b) for a, b in budgets() if (not arms or a in arms) and (not steps or b.steps in steps)]


def _todo(args: argparse.Namespace, running: set[Job]) -> list[Job]:
    """The runs still to start, seed-major: seeds 0 to ``--seeds`` - 1 (the same seed set for all, so that every
    claim compares matched seeds) of every (arm, budget) of :func:`_pairs`, that have no result from this world
    (:func:`finished_run`)."""
    return [(name, budget, seed) for seed in range(args.seeds)
            for name, budget in _pairs(args.arms, args.steps, args.batch_size)
            if (name, budget, seed) not in running
            and finished_run(result_path(args.out, name, budget, seed), args.data) is None]  # fmt: skip


def run_all(args: argparse.Namespace) -> None:
    """Every run the arms need, ``--jobs`` at a time; the summary is rewritten (and committed) as each lands.

    Several at a time pays on a GPU, where one batch-1 run leaves the device mostly idle, and on a small CPU too,
    where one run's threads leave its cores partly idle (its data loading, Python and small kernels run on one
    thread); the runs of a pool share the CPU cores (``cpu_count // jobs`` threads each).
    """

    def landed(name: str, budget: Budget, seed: int) -> None:
        write_report(args.out, args)
        if args.commit:
            commit(name, budget, seed, args.out, args.doc if args.doc and args.doc.is_file() else None)

    if args.jobs == 1:
        while todo := _todo(args, set()):
            run_arm(*todo[0], args)
            landed(*todo[0])
        return
    threads = max(1, (os.cpu_count() or 1) // args.jobs)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
        running: dict[Future, Job] = {}
        while True:
            for job in _todo(args, set(running.values()))[: args.jobs - len(running)]:
                running[pool.submit(run_arm, *job, args, threads)] = job
            if not running:
                return
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                job = running.pop(future)
                future.result()  # a failed run stops the study with its error
                landed(*job)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/study-world"))
    parser.add_argument(
        "--steps",
        type=int,
        nargs="+",
        default=None,
        help="only the runs at these budgets (default: every budget a claim needs); with --arms, those arms at these",
    )
    parser.add_argument(
        "--batch-size", type=int, default=1, help="with --arms and --steps: the batch of those runs (default 1)"
    )
    parser.add_argument("--seeds", type=int, default=5, help="seeds per arm, the same for every arm (default 5)")
    parser.add_argument(
        "--arms",
        nargs="+",
        choices=list(ARMS),
        default=None,
        metavar="ARM",
        help="only these arms (default: every arm); with --steps, these arms at those budgets",
    )
    parser.add_argument("--out", type=Path, default=Path("docs/results/study"))
    parser.add_argument("--runs", type=Path, default=Path("runs/study"))
    parser.add_argument(
        "--checkpoint-every",
        type=int,
        default=100,
        help="steps between a run's checkpoints (a killed run resumes from the newest)",
    )
    parser.add_argument(
        "--commit", action="store_true", help="commit each finished run's result file and the summary to git"
    )
    parser.add_argument("--report", action="store_true", help="only rewrite the summary from the finished runs")
    parser.add_argument(
        "--doc",
        type=Path,
        default=Path("docs/results.md"),
        help="the document whose marked tables the summary rewrites (and --commit commits)",
    )
    parser.add_argument("--progress", action="store_true", help="show each run's training progress bar")
    parser.add_argument("--jobs", type=int, default=1, help="runs at a time, each in its own process (default 1)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.report:
        write_report(args.out, args)
        return
    if not args.data.exists():
        print(
            f"[study] simulating {WORLD['scenes']} scenes x {WORLD['frames']} key frames into {args.data}", flush=True
        )
        simulate_dataset(SimConfig(**WORLD), args.data, workers=2)
    run_all(args)
    report = write_report(args.out, args)
    print((args.out / "study.md").read_text())
    print(f"[study] done: {report['hours']}")


if __name__ == "__main__":
    main()
