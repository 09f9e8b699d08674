"""Every zoo model's outputs on one fixed batch, saved, or compared bitwise with a saved set.

    python benchmarks/model_outputs.py save    [--names ...] [--data data/model_outputs] [--out DIR]
    python benchmarks/model_outputs.py compare [--names ...] [--data data/model_outputs] [--out DIR]

For each entry (all of ``zoo.names()`` by default): the weights drawn with seed 0, then on one training sample of a
synthetic world (2 scenes x 2 key frames at 400 x 225 with Occ3D, SurroundOcc and OpenOcc labels, read with the
entry's own data settings and augmentation, cameras ``CAM_FRONT`` and ``CAM_BACK`` to keep the paper-size entries
quick; none for a LiDAR-only entry), with seed 0 before each pass:

* train mode: every tensor of the forward's output and every loss term, and the gradient norm of every parameter;
* eval mode: the forward's output and ``predict``'s semantics.

``save`` writes ``DIR/NAME.pt``; ``compare`` recomputes them and reports, per entry and tensor, whether they are
bitwise equal (and the largest absolute difference when not), writing ``DIR/compare.json``. A refactoring that must
not change behaviour is checked by ``save`` before it and ``compare`` after it, on the same machine and thread
count (``--threads``, 2 by default).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

from occkit import zoo
from occkit.data.collate import collate
from occkit.data.dataset import OccupancyDataset
from occkit.sim.generate import SimConfig, simulate_dataset

CAMERAS = ("CAM_FRONT", "CAM_BACK")


def _world(root: Path) -> Path:
    if not (root / "annotations.json").is_file():
        simulate_dataset(SimConfig(scenes=2, frames=2, seed=0, image_size=(400, 225), surroundocc=True, openocc=True),
                         root)
    return root


def _batch(name: str, root: Path):
    experiment = zoo.experiment(name)
    cameras = CAMERAS if experiment.data.cameras else ()
    data = dataclasses.replace(experiment.data, root=str(root), split="train", cameras=cameras, index=None)
    dataset = OccupancyDataset(data)  # augmentation drawn from (data.seed, epoch 0, index 0)
    return collate([dataset[0]])


def _tensors(value, prefix: str) -> dict[str, torch.Tensor]:
    """The tensors of a ModelOutput / dict / list, flattened to ``prefix.field`` names."""
    found = {}
    if isinstance(value, torch.Tensor):
        found[prefix] = value.detach().clone()
    elif dataclasses.is_dataclass(value):
        for field in dataclasses.fields(value):
            found.update(_tensors(getattr(value, field.name), f"{prefix}.{field.name}"))
    elif isinstance(value, dict):
        for key, item in value.items():
            found.update(_tensors(item, f"{prefix}.{key}"))
    elif isinstance(value, (list, tuple)):
        for position, item in enumerate(value):
            found.update(_tensors(item, f"{prefix}.{position}"))
    return found


def outputs(name: str, root: Path) -> dict[str, torch.Tensor]:
    """Every output tensor of the entry ``name`` on its fixed batch (see the module docstring)."""
    batch = _batch(name, root)
    torch.manual_seed(0)
    model = zoo.build(name).train()
    torch.manual_seed(0)
    # A recurrent history trains on streams: the first frame of its stream, with an empty memory, as occkit train.
    streamed = model.temporal is not None and model.temporal.cfg.streamed_training
    output = model(batch, memory=model.stream()) if streamed else model(batch)
    losses = model.loss(output, batch)
    sum(losses.values()).backward()
    found = {**_tensors(output, "train"), **_tensors(losses, "loss")}
    found.update({f"grad_norm.{n}": p.grad.norm().detach() for n, p in model.named_parameters() if p.grad is not None})
    model.eval()
    torch.manual_seed(0)
    with torch.no_grad():
        found.update(_tensors(model(batch), "eval"))
        found.update(_tensors(model.predict(batch), "predict"))
    return found


def _difference(a: torch.Tensor, b: torch.Tensor) -> str:
    if a.shape != b.shape or a.dtype != b.dtype:
        return f"shape/dtype {tuple(a.shape)} {a.dtype} vs {tuple(b.shape)} {b.dtype}"
    if torch.equal(a, b):
        return "equal"
    return f"max |diff| {float((a.double() - b.double()).abs().max()):.3g}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=("save", "compare"))
    parser.add_argument("--names", nargs="*", default=None, help="zoo entries (default: all)")
    parser.add_argument("--data", default="data/model_outputs", help="synthetic world, simulated when absent")
    parser.add_argument("--out", default="benchmarks/results/model_outputs")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    root, out = _world(Path(args.data)), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report, failed = {}, []
    for name in args.names or zoo.names():
        started = time.perf_counter()
        found = outputs(name, root)
        seconds = time.perf_counter() - started
        if args.mode == "save":
            torch.save(found, out / f"{name}.pt")
            print(f"{name}: {len(found)} tensors saved ({seconds:.1f} s)")
            continue
        saved = torch.load(out / f"{name}.pt", weights_only=True)
        rows = {key: _difference(saved[key], found[key]) if key in found else "missing now"
                for key in sorted(saved.keys() | found.keys())}  # fmt: skip
        rows.update({key: "new" for key in found.keys() - saved.keys()})
        differing = {key: row for key, row in rows.items() if row != "equal"}
        report[name] = {"tensors": len(rows), "differing": differing}
        failed += [name] if differing else []
        print(f"{name}: {len(rows) - len(differing)}/{len(rows)} tensors bitwise equal ({seconds:.1f} s)")
        for key, row in differing.items():
            print(f"    {key}: {row}")
    if args.mode == "compare":
        (out / "compare.json").write_text(json.dumps(report, indent=2) + "\n")
        print(f"{len(report) - len(failed)}/{len(report)} entries bitwise equal; written {out / 'compare.json'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
