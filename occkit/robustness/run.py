"""``occkit robustness``: a trained model scored on the clean split and under every corruption of a suite.

Each case (the clean data, or a corruption at a level) is one pass of :func:`~occkit.engine.evaluate.evaluate_model`
over the split with the corruption set in the dataset config. Its scores are written to ``OUT/cases/<case>.json``
as soon as it finishes, with a fingerprint of everything they depend on (:mod:`~occkit.robustness.cache`: the
model file's bytes, the data settings, tables and label files, the split, the seed, the case, the occkit version);
a run started again reuses every case whose fingerprint matches and computes the rest, so an interrupted run loses
at most the case it was in.

Which cases apply follows what the model reads at inference (its config's ``sensors``, and a temporal stage), not
what the dataset loads: DA-Occ and FlashOcc load LiDAR in training only as a depth target, so the LiDAR corruptions,
``no_lidar`` and ``no_cameras`` are not applicable to them and stay out of mRR and mCE.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from occkit.data.corruptions import CORRUPTIONS
from occkit.data.dataset import OccupancyDataset
from occkit.engine.evaluate import dataset_ray_origins, evaluation_dataset, score_model
from occkit.errors import InputError
from occkit.model_source import ModelSource
from occkit.outputs import write_atomic
from occkit.robustness.cache import (
    CASES_FOLDER,
    cache_context,
    case_fingerprint,
    case_path,
    check_case_paths,
    read_cached,
    write_case,
)
from occkit.robustness.report import METRICS, markdown, plot_resilience, plot_severity, score_summary
from occkit.robustness.suite import CLEAN, Case, model_inputs, not_applicable, parse_suite

__all__ = ["run_robustness", "inference_inputs", "CASES_FOLDER"]

#: What a run writes beside the cache folder.
REPORT_FILES = ("robustness.json", "robustness.md", "resilience.png", "severity.png")


def inference_inputs(model: Any, model_config: Any) -> frozenset[str]:
    """What ``model`` consumes at inference, in the terms of :attr:`~occkit.data.corruptions.Corruption.needs`: the
    sensors its config declares (``sensors``: what its forward reads, not what the data loads for training targets)
    and ``temporal`` when it has a history stage."""
    sensors = {sensor.lower() for sensor in model_config.sensors}
    return model_inputs("cameras" in sensors, "lidar" in sensors, getattr(model, "temporal", None) is not None)


def _check_report_paths(out: Path) -> None:
    """Refuse a folder standing where a report file goes, before any case is computed."""
    for name in REPORT_FILES:
        if (out / name).exists() and not (out / name).is_file():
            raise InputError(f"{out / name} is not a file, where occkit robustness writes its {name}: remove it, "
                             "or choose another --out")  # fmt: skip


def run_robustness(
    model: ModelSource | str | Path,
    out: str | Path,
    data: str | Path | None = None,
    split: str | None = None,
    suite: str = "default",
    baseline: str | Path | None = None,
    workers: int = 2,
    device: str = "cpu",
    rayiou: bool = True,
    seed: int = 0,
    log: Callable[[str], None] = print,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Score ``model`` on the clean split and under every corruption of ``suite`` that applies to it.

    Args:
        model: where the model comes from: an occkit checkpoint (its path), or weights for a zoo entry.
        out: output folder: ``robustness.json``, ``robustness.md``, ``resilience.png``, ``severity.png`` and the
            per-case cache ``cases/``.
        data, split: the dataset root and split (default: the model's data and validation split).
        suite: ``default``, ``quick`` or ``NAME[:LEVEL],...`` (:func:`~occkit.robustness.suite.parse_suite`).
        baseline: the ``robustness.json`` of a baseline model, for the corruption errors (CE, mCE).
        workers: data loading processes.
        rayiou: score RayIoU too (Occ3D labels only).
        seed: seed of every corruption's draws.
        log: receives one line per case as it finishes (or is found in the cache).
        progress: called with (frames done, frames to do in all, case label) after each batch.

    Returns:
        The report written to ``robustness.json``.
    """
    started = time.perf_counter()
    out = Path(out)
    cases_folder = out / CASES_FOLDER
    cases = parse_suite(suite)
    _check_report_paths(out)
    check_case_paths(cases_folder, [CLEAN, *cases])  # before any work: a blocked path would lose a computed case
    cases_folder.mkdir(parents=True, exist_ok=True)
    baseline_report = None
    if baseline is not None:
        try:
            baseline_report = json.loads(Path(baseline).read_text())
            baseline_report["corruptions"]  # noqa: B018 - the key that makes it a robustness report
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise ValueError(f"--baseline {baseline}: not a robustness.json of occkit robustness ({error})") from error
    source = model if isinstance(model, ModelSource) else ModelSource(ckpt=str(model))
    model, experiment = source.load(device)
    clean_data = evaluation_dataset(experiment, data, split or experiment.train.val_split)
    config = dataclasses.replace(clean_data.config, seed=seed)
    inputs = inference_inputs(model, experiment.model)
    skipped: dict[str, dict] = {}  # corruption -> its levels that do not apply, and why
    for case in cases:
        reason = not_applicable(case, inputs)
        if reason is not None:
            skipped.setdefault(case.corruption, {"name": case.corruption, "levels": [], "reason": reason})
            skipped[case.corruption]["levels"].append(case.severity)
    cases = [CLEAN, *(c for c in cases if c.corruption not in skipped)]  # a corruption applies at every level or none
    origins = dataset_ray_origins(clean_data) if rayiou and clean_data.space.rayiou else None
    context = cache_context(source, clean_data, seed, origins is not None)

    results: dict[Case, dict] = {}
    todo = []
    for case in cases:
        fingerprint = case_fingerprint(context, case)
        cached = read_cached(case_path(cases_folder, case), fingerprint)
        if cached is not None:
            results[case] = {**cached, "cached": True}
            log(f"{case.label}: {_scores(cached)} (cached, {cached['seconds']:.0f} s before)")
        else:
            todo.append((case, fingerprint))
    for reason in dict.fromkeys(item["reason"] for item in skipped.values()):
        log(f"not applicable ({reason}): " + ", ".join(item["name"] for item in skipped.values()
                                                       if item["reason"] == reason))  # fmt: skip
    total, done = len(todo) * len(clean_data), 0
    for case, fingerprint in todo:
        dataset = OccupancyDataset(dataclasses.replace(config, corruption=case.corruption,
                                                       corruption_severity=max(case.severity, 1)))  # fmt: skip

        def step(frames: int, case: Case = case) -> None:
            nonlocal done
            done += frames
            if progress is not None:
                progress(done, total, case.label)

        begin = time.perf_counter()
        scores = score_model(model, dataset, rayiou=origins is not None, ray_origins=origins, workers=workers,
                             progress=step)
        result = {key: scores[key] for key in (*METRICS, "per_class_iou", "frames") if key in scores}
        result["seconds"] = time.perf_counter() - begin
        write_case(case_path(cases_folder, case), fingerprint, result)
        results[case] = {**result, "cached": False}
        log(f"{case.label}: {_scores(result)} ({result['seconds']:.0f} s)")

    report = _report(results, list(skipped.values()), baseline_report, {
        "checkpoint": str(source), "model": experiment.architecture, "data": str(config.root),
        "split": config.split, "frames": len(clean_data), "suite": suite, "seed": seed,
        "inputs": sorted(inputs), "baseline": None if baseline is None else str(baseline),
        "seconds": time.perf_counter() - started, "seconds_computed": sum(r["seconds"] for r in results.values()
                                                                          if not r["cached"]),
    })  # fmt: skip
    write_atomic(out / "robustness.json", json.dumps(report, indent=2) + "\n")
    write_atomic(out / "robustness.md", markdown(report))
    plot_resilience(report, out / "resilience.png")
    if plot_severity(report, out / "severity.png") is None:
        (out / "severity.png").unlink(missing_ok=True)  # an earlier run's curves, of another suite
    return report


def _scores(result: dict) -> str:
    text = f"mIoU {100 * result['miou']:.2f}, IoU {100 * result['iou']:.2f}"
    return text + (f", RayIoU {100 * result['rayiou']:.2f}" if "rayiou" in result else "")


def _report(results: dict[Case, dict], skipped: list[dict], baseline: dict | None, header: dict) -> dict:
    """``robustness.json``: the header, the clean scores, each corruption with its levels, RR and CE, mRR, mCE."""
    clean = results.pop(CLEAN)
    corruptions: dict[str, dict] = {}
    for case in sorted(results, key=lambda c: (list(CORRUPTIONS).index(c.corruption), c.severity)):
        corruption = CORRUPTIONS[case.corruption]
        entry = corruptions.setdefault(case.corruption, {"name": corruption.name, "family": corruption.family,
                                                         "summary": corruption.summary, "levels": []})  # fmt: skip
        entry["levels"].append({"severity": case.severity, "label": corruption.labels[case.severity - 1],
                                "params": corruption.levels[case.severity - 1], **results[case]})  # fmt: skip
    entries = list(corruptions.values())
    summary = score_summary(entries, clean, baseline)
    return {**header, "clean": clean, **summary, "corruptions": entries, "not_applicable": skipped}
