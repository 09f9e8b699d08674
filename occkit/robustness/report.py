"""Robustness scores and their report: resilience rate, corruption error, the markdown table and the plots.

The two summary scores are RoboBEV's (Xie et al. 2023, "RoboBEV: Towards Robust Bird's Eye View Perception under
Corruptions", Sec. 3.2), with occupancy's mIoU (also IoU and RayIoU) in place of NDS:

- resilience rate of corruption ``c`` over its levels ``l = 1..L``: ``RR_c = sum_l m_{c,l} / (L * m_clean)``, the
  share of the clean score kept; ``mRR`` is its mean over the corruptions;
- corruption error against a baseline model (its ``robustness.json``):
  ``CE_c = sum_l (1 - m_{c,l}) / sum_l (1 - m^baseline_{c,l})``, below 1 when the model errs less than the baseline
  under ``c``; ``mCE`` is its mean over the corruptions both runs measured at the same levels (RoboBEV prints both
  in percent, as the tables here do).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from occkit.data.corruptions import CORRUPTIONS
from occkit.figure import new_figure, save_figure

__all__ = ["METRICS", "resilience", "corruption_error", "score_summary", "markdown", "plot_resilience",
           "plot_severity"]  # fmt: skip

#: The scores each case records and each summary is computed for; mIoU is the headline one.
METRICS = ("miou", "iou", "rayiou")
_TITLES = {"miou": "mIoU", "iou": "IoU", "rayiou": "RayIoU"}
_FAMILY_COLORS = {"cameras": "C0", "images": "C1", "lidar": "C2", "geometry": "C3", "temporal": "C4"}


def resilience(levels: list[Mapping], clean: Mapping) -> dict[str, float | None]:
    """``RR_c`` per metric from the levels' scores and the clean scores (None where a score is missing or the clean
    score is 0)."""
    out = {}
    for metric in METRICS:
        values = [level.get(metric) for level in levels]
        ok = clean.get(metric) and all(v is not None for v in values)
        out[metric] = float(np.sum(values) / (len(values) * clean[metric])) if ok else None
    return out


def corruption_error(levels: list[Mapping], baseline_levels: list[Mapping]) -> dict[str, float | None]:
    """``CE_c`` per metric against the baseline's scores at the same levels (None where one is missing or the
    baseline scored 1 everywhere)."""
    out = {}
    for metric in METRICS:
        ours = [level.get(metric) for level in levels]
        theirs = [level.get(metric) for level in baseline_levels]
        if any(v is None for v in ours + theirs) or len(ours) != len(theirs):
            out[metric] = None
            continue
        error = float(np.sum(1.0 - np.asarray(theirs)))
        out[metric] = float(np.sum(1.0 - np.asarray(ours)) / error) if error > 0 else None
    return out


def _mean(values: list[float | None]) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def score_summary(corruptions: list[dict], clean: Mapping, baseline: Mapping | None) -> dict:
    """Fill each corruption's ``rr`` (and ``ce`` with a baseline) and return ``mrr`` / ``mce`` per metric.

    Args:
        corruptions: entries of ``robustness.json``'s ``corruptions`` (``levels`` holding scores), changed in place.
        clean: the clean scores.
        baseline: the baseline run's ``robustness.json``, or None.
    """
    theirs = {c["name"]: c for c in baseline["corruptions"]} if baseline is not None else {}
    for corruption in corruptions:
        corruption["rr"] = resilience(corruption["levels"], clean)
        other = theirs.get(corruption["name"])
        levels = [level["severity"] for level in corruption["levels"]]
        if other is None or [level["severity"] for level in other["levels"]] != levels:
            corruption["ce"] = None
        else:
            corruption["ce"] = corruption_error(corruption["levels"], other["levels"])
    mrr = {m: _mean([c["rr"][m] for c in corruptions]) for m in METRICS}
    with_ce = [c for c in corruptions if c["ce"] is not None]
    mce = {m: _mean([c["ce"][m] for c in with_ce]) for m in METRICS} if baseline is not None else None
    return {"mrr": mrr, "mce": mce, "mce_corruptions": [c["name"] for c in with_ce] if baseline is not None else None}


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.2f}"


def markdown(report: Mapping) -> str:
    """``robustness.md``: the clean scores, one row per corruption (its levels' mIoU, RR, CE), then every level."""
    clean = report["clean"]
    lines = [
        f"# Robustness of `{report['checkpoint']}`",
        "",
        f"{report['model']} on `{report['data']}`, split {report['split']}, {report['frames']} frames; suite "
        f"{report['suite']}, seed {report['seed']}. Scores in percent; RR and CE as RoboBEV defines them "
        "(docs/robustness.md).",
        "",
        f"Clean: mIoU {_pct(clean['miou'])}, IoU {_pct(clean['iou'])}, RayIoU {_pct(clean.get('rayiou'))}.",
        "",
    ]
    summary = f"mRR (mIoU) {_pct(report['mrr']['miou'])}"
    if report.get("mce") is not None:
        summary += f", mCE (mIoU) {_pct(report['mce']['miou'])} against `{report['baseline']}` over " \
                   f"{len(report['mce_corruptions'])} corruptions"  # fmt: skip
    lines += [summary + ".", ""]
    has_ce = report.get("mce") is not None
    header = ["corruption", "family", "mIoU per level", "mean mIoU", "RR mIoU", "RR IoU", "RR RayIoU"]
    header += ["CE mIoU"] if has_ce else []
    lines += ["| " + " | ".join(header) + " |", "| --- | --- | --- |" + " ---: |" * (len(header) - 3)]
    for c in report["corruptions"]:
        levels = " / ".join(_pct(level["miou"]) for level in c["levels"])
        mean = _pct(_mean([level["miou"] for level in c["levels"]]))
        row = [f"`{c['name']}`", c["family"], levels, mean, *(_pct(c["rr"][m]) for m in METRICS)]
        row += [_pct(c["ce"]["miou"]) if c["ce"] is not None else "n/a"] if has_ce else []
        lines.append("| " + " | ".join(row) + " |")
    if report.get("not_applicable"):
        lines += ["", "Not applicable to this model: " + "; ".join(
            f"`{item['name']}` ({item['reason']})" for item in report["not_applicable"]) + "."]  # fmt: skip
    lines += ["", "## Every level", "", "| corruption | level | mIoU | IoU | RayIoU | seconds |",
              "| --- | --- | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for c in report["corruptions"]:
        for level in c["levels"]:
            cached = " (cached)" if level.get("cached") else ""
            lines.append(f"| `{c['name']}` | {level['severity']}: {level['label']} | {_pct(level['miou'])} | "
                         f"{_pct(level['iou'])} | {_pct(level.get('rayiou'))} | {level['seconds']:.0f}{cached} |")
    return "\n".join(lines) + "\n"


def plot_resilience(report: Mapping, path: Path) -> Path:
    """Bars of each corruption's resilience rate (mIoU), coloured by family; 100% is the clean score."""
    corruptions = report["corruptions"]
    figure = new_figure(max(6.0, 0.45 * len(corruptions) + 2), 4.2, layout="constrained")
    axes = figure.add_subplot()
    values = [100 * (c["rr"]["miou"] or 0.0) for c in corruptions]
    axes.bar(range(len(corruptions)), values, color=[_FAMILY_COLORS[c["family"]] for c in corruptions])
    axes.axhline(100, color="black", linewidth=0.8, linestyle="--")
    axes.set_xticks(range(len(corruptions)), [c["name"] for c in corruptions], rotation=60, ha="right")
    axes.set_ylabel("resilience rate, mIoU (%)")
    axes.set_title(f"{report['model']}: mIoU kept under each corruption (mean over its levels)")
    for family, color in _FAMILY_COLORS.items():
        if any(c["family"] == family for c in corruptions):
            axes.bar([], [], color=color, label=family)
    axes.legend(loc="lower left", fontsize=8)
    return save_figure(figure, path)


def plot_severity(report: Mapping, path: Path) -> Path | None:
    """mIoU from the clean data (severity 0) through each level run, for the corruptions whose levels are
    severities, one panel per family. None (no file) when no such corruption was run."""
    ordered = [c for c in report["corruptions"] if CORRUPTIONS[c["name"]].ordered]
    families = [f for f in _FAMILY_COLORS if any(c["family"] == f for c in ordered)]
    if not families:
        return None
    figure = new_figure(4.0 * len(families), 3.6, layout="constrained")
    clean = 100 * report["clean"]["miou"]
    for index, family in enumerate(families):
        axes = figure.add_subplot(1, len(families), index + 1)
        for c in (c for c in ordered if c["family"] == family):
            axes.plot([0] + [lv["severity"] for lv in c["levels"]], [clean] + [100 * lv["miou"] for lv in c["levels"]],
                      marker="o", label=c["name"])  # fmt: skip
        axes.set_title(family)
        axes.set_xlabel("severity (0: clean)")
        axes.set_xticks([0, 1, 2, 3])
        axes.set_ylabel("mIoU (%)")
        axes.set_ylim(bottom=0)
        axes.legend(fontsize=7)
    return save_figure(figure, path)
