"""What a training run writes besides checkpoints: CSV and JSON-lines logs, TensorBoard events and PNG plots."""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from pathlib import Path

__all__ = ["RunLog", "plot_losses"]


class RunLog:
    """Append-only logs of one run in ``folder``: ``train.csv``, ``log.jsonl``, ``val.jsonl`` and ``tensorboard/``.

    Reopening a folder (``--resume``) appends; rows past the resumed step (and a line torn by a kill) are dropped
    first, so a run killed after a log line but before its checkpoint leaves no duplicated steps.
    """

    def __init__(self, folder: str | Path, resume_step: int | None = None) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        if resume_step is not None:
            for name in ("log.jsonl", "val.jsonl"):
                self._truncate(self.folder / name, resume_step)
        from torch.utils.tensorboard import SummaryWriter

        self.tensorboard = SummaryWriter(str(self.folder / "tensorboard"), purge_step=resume_step)
        self._columns: list[str] | None = None
        if resume_step is not None:
            self._rewrite_csv()  # drop the rows past the resumed step from the CSV too

    @staticmethod
    def _truncate(path: Path, step: int) -> None:
        if not path.is_file():
            return
        kept = []
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except ValueError:  # the torn last line of a run killed while appending
                continue
            if row["step"] <= step:
                kept.append(line)
        temporary = path.with_name(f".{path.name}.tmp")
        temporary.write_text("".join(line + "\n" for line in kept))
        temporary.replace(path)  # killed again now, the log is still whole

    def _append(self, name: str, row: Mapping) -> None:
        with open(self.folder / name, "a") as handle:
            handle.write(json.dumps(row) + "\n")

    def train(self, row: Mapping[str, float]) -> None:
        """One training log row: ``step``, ``epoch``, ``lr``, loss terms, ``samples_per_s``."""
        self._append("log.jsonl", row)
        for key, value in row.items():
            if key != "step":
                self.tensorboard.add_scalar(f"train/{key}", value, row["step"])
        if self._columns is not None and list(row) == self._columns:
            with open(self.folder / "train.csv", "a", newline="") as handle:
                csv.DictWriter(handle, fieldnames=self._columns).writerow(row)
        else:
            self._rewrite_csv()

    def validation(self, step: int, metrics: Mapping) -> None:
        """Validation scores: ``miou``, ``iou`` and ``per_class_iou``."""
        self._append("val.jsonl", {"step": step, **metrics})
        self.tensorboard.add_scalar("val/miou", metrics["miou"], step)
        self.tensorboard.add_scalar("val/iou", metrics["iou"], step)
        for name, value in metrics["per_class_iou"].items():
            if value is not None:
                self.tensorboard.add_scalar(f"val_class/{name}", value, step)

    def _rewrite_csv(self) -> None:
        # Written whole from log.jsonl, only when the columns change (a loss term appearing later) or on resume, so
        # the header stays consistent; rows with the same columns are appended.
        rows = self.rows("log.jsonl")
        columns = list(dict.fromkeys(key for row in rows for key in row))
        self._columns = columns
        with open(self.folder / "train.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)

    def rows(self, name: str) -> list[dict]:
        path = self.folder / name
        return [json.loads(line) for line in path.read_text().splitlines() if line] if path.is_file() else []

    def close(self) -> None:
        self.tensorboard.close()


def plot_losses(rows: list[dict], path: str | Path) -> None:
    """Loss terms and their sum against the step, one PNG."""
    from occkit.figure import new_figure, save_figure

    terms = [k for k in (rows[0] if rows else {}) if k.startswith("loss")]
    fig = new_figure(7, 4, dpi=120)
    ax = fig.add_subplot()
    for term in terms:
        ax.plot([r["step"] for r in rows], [r[term] for r in rows], label=term.removeprefix("loss/") or "total")
    ax.set_xlabel("optimizer step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
