"""Bitwise repeatability of CPU training with several threads, and what the fixed-order gradient sums cost.

    python benchmarks/determinism.py [--models flashocc_tiny daocc_tiny] [--steps 20] [--threads 2] [--seed 0]
        [--cost-models flashocc_tiny daocc_tiny da_occ_tiny] [--pairs 10] [--data data/determinism]
        [--device cpu] [--work DIR] [--out benchmarks/results/determinism.json]

1. **repeat**: each of ``--models`` trained ``--steps`` steps twice by ``occkit train`` in fresh processes with
   ``--threads`` threads each; the final checkpoints must be bitwise equal (weights, buffers, EMA, optimizer state,
   random generators).
2. **kill and resume**: a third run is SIGKILLed at a random step past its first checkpoint (a random fraction of a
   step after it was logged) and restarted with ``--resume auto``; it must end bitwise equal to the first run.
3. **cost**: in this process, with ``--threads`` threads, training steps (forward, loss, backward, AdamW) of each of
   ``--cost-models`` on one real batch, interleaved between three variants: ``fixed-order`` (the models as they are:
   gathers through ``occkit.models.indexing.take``, whose gradient is summed in a fixed order), ``indexing`` (``take``
   swapped for advanced indexing ``x[index]``, the previous code, whose gradient sum follows thread scheduling) and
   ``indexing+deterministic`` (the previous code under ``torch.use_deterministic_algorithms(True)``, which makes
   that kernel serial). ``ratio`` = median step time of a variant / median of ``indexing``.

With ``--device cuda`` every part runs on the GPU (``CUBLAS_WORKSPACE_CONFIG`` is set for the deterministic
variant); a variant that PyTorch refuses under deterministic algorithms is recorded with its error. occkit promises
bitwise repeatability on the CPU only; on CUDA the script measures how far two runs drift apart.

The dataset (2 scenes x 8 key frames at 400 x 225, six cameras; the first scene trains) is simulated into ``--data``
when absent. The load average before and after is recorded: on a shared machine only the interleaved timings of
part 3 compare with each other.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from occkit import zoo
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.engine.checkpoint import latest_checkpoint, load_checkpoint
from occkit.machine import machine_info

#: The modules whose gathers go through ``take``; part 3 swaps the name in each.
MODULES_WITH_TAKE = ("occkit.models.view_transform.lss", "occkit.models.dac", "occkit.models.sparse_rules")
VARIANTS = ("fixed-order", "indexing", "indexing+deterministic")


# ------------------------------------------------------------------------------------------------------ training runs
def _train(model: str, data: Path, out: Path, steps: int, threads: int, device: str,
           resume: bool = False) -> subprocess.Popen:
    sets = (f"data.root={data}", f"train.max_steps={steps}", "train.val_every=-1", "train.checkpoint_every=2",
            "train.log_every=1", "train.keep_last=2")  # fmt: skip
    command = [sys.executable, "-m", "occkit", "train", "--config", model, "--out", str(out), "--no-progress",
               "--device", device, *(part for value in sets for part in ("--set", value))]  # fmt: skip
    if resume:
        command += ["--resume", "auto"]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    with open(out.parent / f"{out.name}.stderr", "ab") as stderr:
        return subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=stderr)


def _wait(process: subprocess.Popen, out: Path) -> None:
    if process.wait() != 0:
        raise RuntimeError(f"occkit train --out {out} exited {process.returncode}:\n"
                           f"{(out.parent / f'{out.name}.stderr').read_text()[-3000:]}")  # fmt: skip


def _logged_step(out: Path) -> int:
    step = 0
    for line in (out / "log.jsonl").read_text().splitlines() if (out / "log.jsonl").is_file() else []:
        with contextlib.suppress(ValueError):  # a line being written
            step = json.loads(line)["step"]
    return step


def _kill_at(process: subprocess.Popen, out: Path, step: int, rng: random.Random) -> float:
    """SIGKILL once ``out`` has a checkpoint and has logged ``step``, a random delay later; the delay in seconds."""
    while not ((out / "last.json").is_file() and _logged_step(out) >= step):
        if process.poll() is not None:
            raise RuntimeError(f"the run ended before step {step}")
        time.sleep(0.01)
    delay = rng.uniform(0.0, 1.0)
    time.sleep(delay)
    if process.poll() is not None:
        raise RuntimeError("the run ended before it could be killed")
    process.send_signal(signal.SIGKILL)
    process.wait()
    return delay


def _differences(a: dict, b: dict) -> tuple[int, list[str]]:
    """Tensors and values compared between two checkpoints, and the names of those that differ."""
    pairs = [(f"model.{k}", a["model"][k], b["model"].get(k)) for k in a["model"]]
    pairs += [(f"ema.{k}", v, (b.get("ema") or {}).get(k)) for k, v in (a.get("ema") or {}).items()]
    for index, state in a["optimizer"]["state"].items():
        other = b["optimizer"]["state"].get(index, {})
        pairs += [(f"optimizer.{index}.{k}", v, other.get(k)) for k, v in state.items()]
    pairs += [("rng.torch", a["rng"]["torch"], b["rng"]["torch"]),
              ("rng.numpy", a["rng"]["numpy"]["keys"], b["rng"]["numpy"]["keys"]),
              ("rng.python", a["rng"]["python"], b["rng"]["python"]), ("step", a["step"], b["step"])]  # fmt: skip
    differ = [name for name, x, y in pairs
              if not (torch.equal(x, y) if isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor) else x == y)]
    return len(pairs), differ


def check_runs(model: str, data: Path, work: Path, steps: int, threads: int, device: str,
               rng: random.Random) -> dict:
    """Parts 1 and 2 for one model."""
    first, second, killed = (work / f"{model}-{name}" for name in ("first", "second", "killed"))
    seconds = {}
    for out in (first, second):
        started = time.perf_counter()
        _wait(_train(model, data, out, steps, threads, device), out)
        seconds[out.name] = time.perf_counter() - started
    reference = load_checkpoint(latest_checkpoint(first))
    compared, repeat_differ = _differences(reference, load_checkpoint(latest_checkpoint(second)))

    kill_step = rng.randint(3, steps - 3)
    started = time.perf_counter()
    delay = _kill_at(_train(model, data, killed, steps, threads, device), killed, kill_step, rng)
    resumed_from = json.loads((killed / "last.json").read_text())["step"]
    logged_at_kill = _logged_step(killed)
    _wait(_train(model, data, killed, steps, threads, device, resume=True), killed)
    seconds[killed.name] = time.perf_counter() - started
    _, resume_differ = _differences(reference, load_checkpoint(latest_checkpoint(killed)))
    return {
        "compared": compared,
        "repeat_bitwise_equal": not repeat_differ,
        "repeat_differ": repeat_differ,
        "killed_after_step": logged_at_kill,
        "kill_delay_s": round(delay, 3),
        "resumed_from_checkpoint": resumed_from,
        "resume_bitwise_equal": not resume_differ,
        "resume_differ": resume_differ,
        "run_seconds": {k: round(v, 1) for k, v in seconds.items()},
    }


# ------------------------------------------------------------------------------------------------------ cost
def _advanced_indexing(source: torch.Tensor, index: torch.Tensor, dim: int = 0) -> torch.Tensor:
    """``take`` as the models computed it before: its backward is ``index_put_(accumulate=True)``."""
    return source[(slice(None),) * (dim % source.dim()) + (index,)]


@contextlib.contextmanager
def variant(name: str):
    """Run the models as ``name`` (one of :data:`VARIANTS`) inside the block."""
    modules = []
    for module_name in MODULES_WITH_TAKE:
        try:
            modules.append(importlib.import_module(module_name))
        except ImportError:  # sparse_rules without spconv: no model of the run uses it
            continue
    saved = [m.take for m in modules]
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    try:
        if name != "fixed-order":
            for module in modules:
                module.take = _advanced_indexing
        torch.use_deterministic_algorithms(name == "indexing+deterministic")
        yield
    finally:
        for module, take in zip(modules, saved, strict=True):
            module.take = take
        torch.use_deterministic_algorithms(was_deterministic)


def measure_cost(model_name: str, data: Path, pairs: int, warmup: int, device: str) -> dict:
    experiment = zoo.experiment(model_name)
    dataset = OccupancyDataset(replace(experiment.data, root=str(data)))
    batch = collate([dataset[0]]).to(device)
    torch.manual_seed(0)
    model = zoo.build(model_name).to(device).train()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)

    def step(name: str) -> float:
        with variant(name):
            if device != "cpu":
                torch.cuda.synchronize()
            start = time.perf_counter()
            loss = sum(model.loss(model(batch), batch).values())
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            if device != "cpu":
                torch.cuda.synchronize()
            return time.perf_counter() - start

    refused = {}
    for name in VARIANTS:
        try:
            step(name)
        except RuntimeError as error:  # e.g. a CUDA kernel without a deterministic implementation
            refused[name] = str(error).splitlines()[0]
    variants = [name for name in VARIANTS if name not in refused]
    for name in variants * (warmup - 1):
        step(name)
    times: dict[str, list[float]] = {name: [] for name in variants}
    for index in range(pairs):  # the order rotates from round to round, so that a load change hits all alike
        for name in variants[index % len(variants):] + variants[: index % len(variants)]:
            times[name].append(step(name))
    medians = {name: statistics.median(t) for name, t in times.items()}
    return {
        "median_step_s": {k: round(v, 4) for k, v in medians.items()},
        "ratio_to_indexing": {k: round(v / medians["indexing"], 3) for k, v in medians.items()},
        "step_s": {k: [round(t, 4) for t in v] for k, v in times.items()},
        "refused": refused,
    }


# ------------------------------------------------------------------------------------------------------ main
def _verdict(differ: list[str]) -> str:
    return "bitwise equal" if not differ else f"{len(differ)} DIFFER, e.g. {', '.join(differ[:3])}"


def _ensure_data(root: Path) -> None:
    if (root / "v1.0-synth").is_dir():
        return
    from occkit.sim.generate import SimConfig, simulate_dataset

    print(f"simulating 2 scenes x 8 key frames into {root} ...", flush=True)
    simulate_dataset(SimConfig(scenes=2, frames=8, seed=0, image_size=(400, 225)), root)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="*", default=["flashocc_tiny", "daocc_tiny"], choices=zoo.names())
    parser.add_argument("--cost-models", nargs="*", default=["flashocc_tiny", "daocc_tiny", "da_occ_tiny"],
                        choices=zoo.names())  # fmt: skip
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--pairs", type=int, default=10, help="timed rounds of the three variants in part 3")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0, help="draws the kill moments")
    parser.add_argument("--data", type=Path, default=Path("data/determinism"))
    parser.add_argument("--device", default="cpu", help="cpu or cuda: where the runs and the timed steps go")
    parser.add_argument("--work", type=Path, default=None, help="run folders (default: a temporary folder)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/determinism.json"))
    args = parser.parse_args()
    if args.steps < 6:
        parser.error("--steps must be at least 6 (a checkpoint every 2 steps, a kill between steps 3 and steps - 3)")

    if args.device != "cpu":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # cuBLAS's condition for deterministic GEMMs
    args.data = args.data.resolve()
    _ensure_data(args.data)
    torch.set_num_threads(args.threads)
    machine = machine_info(args.device)
    result: dict = {
        "torch": machine["torch"],
        "threads": args.threads,
        "device": machine["device"],
        "cpu_count": machine["cpu_count"],
        "processor": machine["cpu"],
        "load_average_before": [round(x, 2) for x in os.getloadavg()],
        "steps": args.steps,
        "seed": args.seed,
        "runs": {},
        "cost": {},
    }
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as temporary:
        work = args.work or Path(temporary)
        work.mkdir(parents=True, exist_ok=True)
        for name in args.models:
            runs = check_runs(name, args.data, work, args.steps, args.threads, args.device, rng)
            result["runs"][name] = runs
            print(f"{name}: two runs of {args.steps} steps with {args.threads} threads "
                  f"{_verdict(runs['repeat_differ'])} ({runs['compared']} tensors and values); killed after step "
                  f"{runs['killed_after_step']} (+{runs['kill_delay_s']} s), resumed from step "
                  f"{runs['resumed_from_checkpoint']}: {_verdict(runs['resume_differ'])}; "
                  f"seconds {runs['run_seconds']}", flush=True)  # fmt: skip
    for name in args.cost_models:
        cost = measure_cost(name, args.data, args.pairs, args.warmup, args.device)
        result["cost"][name] = cost
        print(f"{name}: median step " + ", ".join(f"{k} {v:.3f} s" for k, v in cost["median_step_s"].items())
              + "; ratio to indexing " + ", ".join(f"{k} {v:.3f}" for k, v in cost["ratio_to_indexing"].items())
              + "".join(f"; {k} refused: {v}" for k, v in cost["refused"].items()),
              flush=True)  # fmt: skip
    result["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    # None when no run was compared (--models with no name: the cost part alone).
    result["all_bitwise_equal"] = all(r["repeat_bitwise_equal"] and r["resume_bitwise_equal"]
                                      for r in result["runs"].values()) if result["runs"] else None  # fmt: skip
    verdict = "" if result["runs"] == {} else f"; all bitwise equal: {result['all_bitwise_equal']}"
    print(f"load average before {result['load_average_before']}, after {result['load_average_after']}{verdict}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    sys.exit(1 if result["all_bitwise_equal"] is False else 0)


if __name__ == "__main__":
    main()
