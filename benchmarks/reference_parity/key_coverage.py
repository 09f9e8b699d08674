"""How ``occkit convert`` covers the reference models' paper-size state dicts, key by key.

    python benchmarks/reference_parity/key_coverage.py [docs/results/parity/NAME.json ...]

Each ``docs/results/parity/NAME.json`` is a key list a harness script (``flashocc_model.py``, ``daocc_model.py``)
wrote from the reference model itself: every state-dict key with its shape. ``NAME`` is the zoo entry it converts to.
For each, this converts a state dict of those keys and shapes (tensors on the meta device, no memory; BatchNorm's
``num_batches_tracked`` int64, all else float32 as the references save them) onto the entry's model with occkit's
conversion tables, and writes ``NAME.coverage.json``: per key its occkit name and the re-layout made, or the reason
it is dropped, and the totals. ``tests/test_reference_parity_models.py`` recomputes it and requires it to be current
and complete (0 unmapped keys, 0 shape mismatches, no occkit tensor left unfilled).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from occkit.convert import convert_state_dict

PARITY = Path(__file__).resolve().parents[2] / "docs" / "results" / "parity"


def key_lists(folder: Path = PARITY) -> list[Path]:
    """The key lists in ``folder`` (not the coverage files written beside them)."""
    return sorted(path for path in folder.glob("*.json") if not path.name.endswith(".coverage.json"))


def coverage(key_list: Path) -> dict:
    """The coverage of ``key_list`` by the conversion to the zoo entry its file is named after."""
    listed = json.loads(key_list.read_text())
    state = {key: torch.empty(shape, device="meta",
                              dtype=torch.int64 if key.endswith("num_batches_tracked") else torch.float32)
             for key, shape in listed["keys"].items()}  # fmt: skip
    entry = key_list.stem
    conversion = convert_state_dict(state, entry, strict=False)
    mismatched = {m.reference_key: m for m in conversion.shape_mismatches}
    by_key = {}
    for key, shape in listed["keys"].items():
        if key in conversion.mapped:
            name = conversion.mapped[key]
            by_key[key] = {"shape": shape, "occkit": name, "relayout": conversion.transforms.get(name)}
        elif key in conversion.dropped:
            by_key[key] = {"shape": shape, "dropped": conversion.dropped[key]}
        elif key in mismatched:
            by_key[key] = {"shape": shape, "occkit": mismatched[key].key,
                            "occkit_shape": list(mismatched[key].occkit_shape)}  # fmt: skip
        else:
            by_key[key] = {"shape": shape, "unmapped": conversion.unmapped.get(key, "not converted")}
    return {
        "reference": listed["reference"],
        "entry": entry,
        "keys": len(listed["keys"]),
        "mapped": len(conversion.mapped),
        "dropped": len(conversion.dropped),
        "unmapped": len(conversion.unmapped),
        "shape_mismatches": len(conversion.shape_mismatches),
        "occkit_unfilled": sorted(conversion.missing),
        "covered": f"{100.0 * (len(conversion.mapped) + len(conversion.dropped)) / len(listed['keys']):.1f}%",
        "by_key": by_key,
    }


def coverage_path(key_list: Path) -> Path:
    return key_list.with_name(f"{key_list.stem}.coverage.json")


def main(paths: list[str]) -> int:
    incomplete = 0
    for key_list in [Path(p) for p in paths] or key_lists():
        report = coverage(key_list)
        coverage_path(key_list).write_text(json.dumps(report, indent=1) + "\n")
        print(f"{report['entry']}: {report['keys']} reference keys, {report['mapped']} mapped, {report['dropped']} "
              f"dropped with a reason, {report['unmapped']} unmapped, {report['shape_mismatches']} shape mismatches, "
              f"{len(report['occkit_unfilled'])} occkit tensors unfilled ({report['covered']} covered)")  # fmt: skip
        incomplete += bool(report["unmapped"] or report["shape_mismatches"] or report["occkit_unfilled"])
    return 1 if incomplete else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
