"""``occkit robustness``: a trained model scored on the clean split and under every corruption of a suite.

Each case (the clean data, or a corruption at a level) is one pass of :func:`~occkit.engine.evaluate.evaluate_model`
over the split with the corruption set in the dataset config. Its scores are written to ``OUT/cases/<case>.json``
as soon as it finishes, with a fingerprint of everything they depend on (the checkpoint's bytes, the data, the
split, the seed, the corruption's parameters, the metric settings); a run started again reuses every case whose
fingerprint matches and computes the rest, so an interrupted run loses at most the case it was in.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

from occkit import __version__
from occkit.data.corruptions import CORRUPTIONS
from occkit.data.dataset import OccupancyDataset
from occkit.data.index import tables_key
from occkit.engine.checkpoint import atomic_write_text
from occkit.engine.evaluate import dataset_ray_origins, evaluate_model, evaluation_dataset, load_trained
from occkit.robustness.report import METRICS, markdown, plot_resilience, plot_severity, score_summary
from occkit.robustness.suite import CLEAN, Case, model_inputs, not_applicable, parse_suite

__all__ = ["run_robustness", "CASES_FOLDER"]

#: Where each case's scores are cached, inside the output folder.
CASES_FOLDER = "cases"


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _library_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _fingerprint(common: dict[str, Any], case: Case) -> dict[str, Any]:
    """What a case's scores depend on; a cached case is reused only when its fingerprint is equal."""
    fingerprint = {**common, "case": case.key}
    if case.corruption is not None:
        corruption = CORRUPTIONS[case.corruption]
        fingerprint["params"] = corruption.levels[case.severity - 1]
        if corruption.family == "images":  # the pixels are the library's
            fingerprint["albumentations"] = _library_version("albumentations")
    return json.loads(json.dumps(fingerprint))  # tuples -> lists, as read back from the file


def _read_cached(path: Path, fingerprint: dict) -> dict | None:
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # absent, or cut short by a kill before the rename (never: it is written atomically)
    return entry if entry.get("fingerprint") == fingerprint else None


def run_robustness(
    checkpoint: str | Path,
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
    """Score ``checkpoint`` on the clean split and under every corruption of ``suite`` that applies to it.

    Args:
        checkpoint: an occkit checkpoint.
        out: output folder: ``robustness.json``, ``robustness.md``, ``resilience.png``, ``severity.png`` and the
            per-case cache ``cases/``.
        data, split: the dataset root and split (default: the checkpoint's data and validation split).
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
    cases_folder.mkdir(parents=True, exist_ok=True)
    baseline_report = None
    if baseline is not None:
        try:
            baseline_report = json.loads(Path(baseline).read_text())
            baseline_report["corruptions"]  # noqa: B018 - the key that makes it a robustness report
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise ValueError(f"--baseline {baseline}: not a robustness.json of occkit robustness ({error})") from error
    cases = parse_suite(suite)
    model, experiment = load_trained(checkpoint, device)
    clean_data = evaluation_dataset(experiment, data, split or experiment.train.val_split)
    config = dataclasses.replace(clean_data.config, seed=seed)
    inputs = model_inputs(bool(config.cameras), config.sweeps >= 0, getattr(model, "temporal", None) is not None)
    skipped: dict[str, dict] = {}  # corruption -> its levels that do not apply, and why
    for case in cases:
        reason = not_applicable(case, inputs)
        if reason is not None:
            skipped.setdefault(case.corruption, {"name": case.corruption, "levels": [], "reason": reason})
            skipped[case.corruption]["levels"].append(case.severity)
    cases = [CLEAN, *(c for c in cases if c.corruption not in skipped)]  # a corruption applies at every level or none
    origins = dataset_ray_origins(clean_data) if rayiou and clean_data.space.rayiou else None
    root = Path(config.root).resolve()
    common = {"checkpoint_sha256": _sha256(Path(checkpoint)), "data": str(root), "version": config.version,
              "tables": tables_key(root, config.version, 0), "split": config.split, "frames": len(clean_data),
              "seed": seed, "rayiou": origins is not None, "occkit": __version__}  # fmt: skip

    results: dict[Case, dict] = {}
    todo = []
    for case in cases:
        fingerprint = _fingerprint(common, case)
        cached = _read_cached(cases_folder / f"{case.key}.json", fingerprint)
        if cached is not None:
            results[case] = {**cached["result"], "cached": True}
            log(f"{case.label}: {_scores(cached['result'])} (cached, {cached['result']['seconds']:.0f} s before)")
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
        scores = evaluate_model(model, dataset, 1, workers, ray_origins=origins, progress=step)
        result = {key: scores[key] for key in (*METRICS, "per_class_iou", "frames") if key in scores}
        result["seconds"] = time.perf_counter() - begin
        atomic_write_text(json.dumps({"fingerprint": fingerprint, "result": result}, indent=2) + "\n",
                          cases_folder / f"{case.key}.json")  # fmt: skip
        results[case] = {**result, "cached": False}
        log(f"{case.label}: {_scores(result)} ({result['seconds']:.0f} s)")

    report = _report(results, list(skipped.values()), baseline_report, {
        "checkpoint": str(checkpoint), "model": experiment.architecture, "data": str(config.root),
        "split": config.split, "frames": len(clean_data), "suite": suite, "seed": seed,
        "inputs": sorted(inputs), "baseline": None if baseline is None else str(baseline),
        "seconds": time.perf_counter() - started, "seconds_computed": sum(r["seconds"] for r in results.values()
                                                                          if not r["cached"]),
    })  # fmt: skip
    atomic_write_text(json.dumps(report, indent=2) + "\n", out / "robustness.json")
    atomic_write_text(markdown(report), out / "robustness.md")
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
