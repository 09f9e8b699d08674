"""Fusion against each sensor alone under corruptions: the worked comparison of docs/robustness.md.

    python benchmarks/robustness_comparison.py [--data data/study-world] [--suite default] [--runs runs/study]
    python benchmarks/robustness_comparison.py --sheet docs/images/corruptions.jpg

Scores the seed-0 checkpoints of three arms of ``benchmarks/study.py`` (``daocc_tiny``: camera + LiDAR fusion, and
the same network with its LiDAR branch alone and with its camera branch alone; one recipe, one budget, one world)
with ``occkit robustness`` on the world's held-out scenes, the fusion model as the CE baseline of the other two.
Each model's run caches every case in ``runs/robustness/<arm>/cases``: the script resumes where it stopped. Writes
``docs/results/robustness/``: ``comparison.json`` (the three reports), ``comparison.md``, ``resilience.png``,
``severity.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from matplotlib.lines import Line2D
from tqdm import tqdm

from occkit.data.corruptions import CORRUPTIONS
from occkit.data.names import folder_name
from occkit.figure import new_figure, save_figure
from occkit.robustness import run_robustness

#: Arm of benchmarks/study.py -> what it is; the first is the CE baseline.
MODELS = {
    "daocc_tiny": "fusion (camera + LiDAR)",
    "daocc_tiny LiDAR only": "LiDAR only",
    "daocc_tiny camera only": "camera only",
}


def _pct(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.1f}"


def comparison_markdown(reports: dict[str, dict], args: argparse.Namespace) -> str:
    names = list(reports)
    first = reports[names[0]]
    lines = [
        "# Robustness: fusion against each sensor alone",
        "",
        f"`python benchmarks/robustness_comparison.py --data {args.data} --suite {args.suite}`: the seed-0 "
        f"checkpoints of the study's arms, {first['frames']} held-out frames (split {first['split']}), corruption "
        f"seed {first['seed']}. mIoU in percent, mean over a corruption's levels; RR = mIoU kept, CE = error "
        f"relative to `{names[0]}` (RoboBEV's definitions, docs/robustness.md). n/a: the corruption needs an input "
        "the model does not take.",
        "",
        "| | " + " | ".join(f"{MODELS[n]}: mIoU | RR | CE" for n in names) + " |",
        "| --- |" + " ---: | ---: | ---: |" * len(names),
    ]
    clean = " | ".join(f"{_pct(reports[n]['clean']['miou'])} | | " for n in names)
    lines.append(f"| clean | {clean} |")
    by_name = {n: {c["name"]: c for c in reports[n]["corruptions"]} for n in names}
    for corruption in CORRUPTIONS:
        if not any(corruption in by_name[n] for n in names):
            continue
        cells = []
        for n in names:
            c = by_name[n].get(corruption)
            if c is None:
                cells += ["n/a", "", ""]
                continue
            mean = sum(level["miou"] for level in c["levels"]) / len(c["levels"])
            ce = c["ce"]["miou"] if c.get("ce") else None
            cells += [_pct(mean), _pct(c["rr"]["miou"]), "" if n == names[0] else _pct(ce)]
        lines.append(f"| `{corruption}` | " + " | ".join(cells) + " |")
    summary = []
    for n in names:
        mce = reports[n].get("mce")
        summary += [_pct(reports[n]["mrr"]["miou"]), "", "" if mce is None else _pct(mce["miou"])]
    lines.append("| **mRR / mCE** | " + " | ".join(summary) + " |")
    lines += ["", "Evaluation time per model, summed over its cases as each was computed (CPU, 2 threads):", ""]
    for n in names:
        levels = [level for c in reports[n]["corruptions"] for level in c["levels"]]
        seconds = reports[n]["clean"]["seconds"] + sum(level["seconds"] for level in levels)
        lines.append(f"- {MODELS[n]}: {seconds / 60:.1f} min for {1 + len(levels)} cases")
    return "\n".join(lines) + "\n"


def plot_resilience(reports: dict[str, dict], path: Path) -> Path:
    names = list(reports)
    corruptions = [c for c in CORRUPTIONS if any(c in {x["name"] for x in reports[n]["corruptions"]} for n in names)]
    figure = new_figure(max(8.0, 0.55 * len(corruptions) + 2), 4.4, layout="constrained")
    axes = figure.add_subplot()
    width = 0.8 / len(names)
    for index, n in enumerate(names):
        rr = {c["name"]: c["rr"]["miou"] for c in reports[n]["corruptions"]}
        xs = [i + (index - (len(names) - 1) / 2) * width for i, c in enumerate(corruptions) if c in rr]
        axes.bar(xs, [100 * rr[c] for c in corruptions if c in rr], width, label=MODELS[n])
    axes.axhline(100, color="black", linewidth=0.8, linestyle="--")
    axes.set_xticks(range(len(corruptions)), corruptions, rotation=60, ha="right")
    axes.set_ylabel("resilience rate, mIoU (%)")
    axes.set_title("mIoU kept under each corruption (mean over its levels)")
    axes.legend(fontsize=8)
    return save_figure(figure, path)


def plot_severity(reports: dict[str, dict], path: Path) -> Path:
    names = list(reports)
    ordered = [c for c, spec in CORRUPTIONS.items() if spec.ordered and len(spec.levels) > 1
               and any(c in {x["name"] for x in reports[n]["corruptions"]} for n in names)]  # fmt: skip
    columns = 5
    rows = -(-len(ordered) // columns)
    figure = new_figure(3.0 * columns, 2.5 * rows, layout="constrained")
    for index, corruption in enumerate(ordered):
        axes = figure.add_subplot(rows, columns, index + 1)
        for model_index, n in enumerate(names):
            entry = {c["name"]: c for c in reports[n]["corruptions"]}.get(corruption)
            if entry is None:
                continue
            xs = [0] + [level["severity"] for level in entry["levels"]]
            ys = [100 * reports[n]["clean"]["miou"]] + [100 * level["miou"] for level in entry["levels"]]
            axes.plot(xs, ys, marker="o", markersize=3, color=f"C{model_index}", label=MODELS[n])
        axes.set_title(corruption, fontsize=9)
        axes.set_xticks(range(4), ["clean", "1", "2", "3"], fontsize=7)
        axes.tick_params(labelsize=7)
        axes.set_ylim(bottom=0)
        if index % columns == 0:
            axes.set_ylabel("mIoU (%)", fontsize=8)
    handles = [Line2D([], [], color=f"C{i}", marker="o", markersize=3, label=MODELS[n]) for i, n in enumerate(names)]
    figure.legend(handles=handles, loc="outside upper center", ncols=len(names), fontsize=8)
    return save_figure(figure, path)


def corruption_sheet(data: Path, path: Path, camera: str = "CAM_FRONT") -> Path:
    """One camera image of the first held-out frame under every image corruption and level, clean first."""
    from PIL import Image, ImageDraw

    from occkit.data.dataset import DatasetConfig, OccupancyDataset

    dataset = OccupancyDataset(DatasetConfig(root=str(data), split="val", sweeps=-1, occupancy=False, boxes=False))
    record = dataset.records[len(dataset.records) // 2]
    clean = dataset._read_camera(record, camera, record.token)
    width, height = clean.size
    names = [name for name, c in CORRUPTIONS.items() if c.family == "images"]
    sheet = Image.new("RGB", (3 * width, (1 + len(names)) * height), "white")
    sheet.paste(clean, (0, 0))
    draw = ImageDraw.Draw(sheet)
    draw.text((6, 4), "clean", fill="yellow")
    for row, name in enumerate(names, start=1):
        for severity in CORRUPTIONS[name].severities:
            corrupted = OccupancyDataset(DatasetConfig(root=str(data), split="val", sweeps=-1, occupancy=False,
                                                       boxes=False, corruption=name, corruption_severity=severity))
            sheet.paste(corrupted._read_camera(record, camera, record.token), ((severity - 1) * width, row * height))
            draw.text(((severity - 1) * width + 6, row * height + 4),
                      f"{name} {CORRUPTIONS[name].labels[severity - 1]}", fill="yellow")  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet = sheet.resize((sheet.width * 2 // 3, sheet.height * 2 // 3), Image.Resampling.LANCZOS)
    sheet.save(path, quality=88)  # a .jpg: a PNG of nine rows of noise weighs megabytes
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/study-world"))
    parser.add_argument("--runs", type=Path, default=Path("runs/study"), help="the study's run folder")
    parser.add_argument("--suite", default="default")
    parser.add_argument("--out", type=Path, default=Path("runs/robustness"))
    parser.add_argument("--docs", type=Path, default=Path("docs/results/robustness"))
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--sheet", type=Path, default=None, metavar="PNG",
                        help="only draw the image corruptions of one camera image into PNG")
    args = parser.parse_args()
    if args.sheet is not None:
        print(f"wrote {corruption_sheet(args.data, args.sheet)}")
        return
    reports: dict[str, dict] = {}
    baseline = None
    for name in MODELS:
        checkpoint = args.runs / folder_name(name) / "500-steps" / "seed-0" / "step-00000500.pt"
        if not checkpoint.is_file():
            sys.exit(f"{checkpoint} not found: train the arm first (python benchmarks/study.py --arms '{name}' "
                     "--steps 500)")  # fmt: skip
        out = args.out / folder_name(name)
        print(f"[robustness] {name}: {checkpoint} -> {out}", flush=True)
        began = time.perf_counter()
        with tqdm(total=0, unit="frame", mininterval=30) as bar:
            def progress(done: int, total: int, label: str, bar=bar) -> None:
                bar.total = total
                bar.set_description(label, refresh=False)
                bar.update(done - bar.n)

            reports[name] = run_robustness(checkpoint, out, data=args.data, suite=args.suite, baseline=baseline,
                                           workers=args.workers, log=tqdm.write, progress=progress)  # fmt: skip
        print(f"[robustness] {name}: {(time.perf_counter() - began) / 60:.1f} min", flush=True)
        baseline = baseline or out / "robustness.json"
    args.docs.mkdir(parents=True, exist_ok=True)
    (args.docs / "comparison.json").write_text(json.dumps(reports, indent=2) + "\n")
    (args.docs / "comparison.md").write_text(comparison_markdown(reports, args))
    plot_resilience(reports, args.docs / "resilience.png")
    plot_severity(reports, args.docs / "severity.png")
    print((args.docs / "comparison.md").read_text())


if __name__ == "__main__":
    main()
