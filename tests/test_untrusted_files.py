"""Files occkit did not write: checkpoints, weights, ``.npz`` predictions and labels are refused on one line when
crafted or broken, from what they declare and before they cost memory, and weights or flows that cannot be right are
named instead of scoring 0 or training to infinity.

The crafted files are tiny on disk: zip bombs of deflated zeros, and archives whose central directory or ``.npy``
header declares more than the file holds. Peak memory is not timed here (``tests/test_bad_input_sweep.py`` measures
it in fresh processes); these tests show the refusal comes from the declarations, before any data is read.
"""

from __future__ import annotations

import os
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import crafting

from occkit import zoo
from occkit.archives import TORCH_SIZE_SLACK, NpzArchive, check_torch_file
from occkit.cli import main
from occkit.convert import convert_checkpoint, read_checkpoint
from occkit.data.labels import MAX_FLOW_SPEED, LabelError, read_occ3d_labels, read_surroundocc_labels
from occkit.engine.checkpoint import FORMAT, load_checkpoint
from occkit.geometry.grid import VoxelGrid
from occkit.metrics.evaluate import evaluate_predictions, read_prediction, read_prediction_flow
from occkit.weight_files import load_torch_file

SMALL = VoxelGrid((-1.6, -1.6, -0.4, 1.6, 1.6, 0.4), 0.4)  # 8 x 8 x 2
TOKEN = "0" * 32


def _one_error_line(argv: list[str], capsys) -> str:
    """Run ``occkit argv``: it must end in exit code 2 and one line on stderr, which is returned."""
    code = main(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip() and "%|" not in line]  # no bars
    assert code == 2 and len(lines) == 1 and "internal error" not in err and "Traceback" not in err, err
    return lines[0]


# ----------------------------------------------------------------------------------------------------- S2: torch files
@pytest.fixture
def torch_bomb(tmp_path) -> Path:
    """torch's zip format with its tensor record replaced by 256 MB of deflated zeros (a file of about 256 KB)."""
    path = tmp_path / "bomb.pt"
    crafting().torch_zip_bomb(path, 256 << 20)
    assert path.stat().st_size < 2 << 20
    return path


def test_a_deflated_torch_record_is_refused_from_its_declared_size(torch_bomb, tmp_path, capsys):
    message = r"bomb\.pt is not a checkpoint torch wrote: its record bomb/data/0 declares 256\.0 MB uncompressed from"
    with pytest.raises(ValueError, match=message):
        check_torch_file(torch_bomb)
    with pytest.raises(ValueError, match=message):  # the converter, eval --weights, the pretrained backbones
        read_checkpoint(torch_bomb)
    with pytest.raises(ValueError, match=message):  # eval / predict / robustness / view --ckpt, train --resume
        load_checkpoint(torch_bomb)
    line = _one_error_line(["convert", str(torch_bomb), "--model", "flashocc_tiny",
                            "--out", str(tmp_path / "c.safetensors")], capsys)  # fmt: skip
    assert "bomb.pt" in line and "bomb/data/0" in line and "256.0 MB" in line


def test_records_declaring_more_than_the_file_holds_are_refused(tmp_path):
    """Stored (uncompressed) records whose central directory claims 64 MB each: no single one inflates, their sum
    is what gives them away (as overlapping records would)."""
    path = tmp_path / "forged.pt"
    torch.save({"a": torch.zeros(4), "b": torch.zeros(4)}, path)
    data = bytearray(path.read_bytes())
    at = data.find(b"PK\x01\x02")
    while at != -1:  # every central directory entry: compressed and uncompressed size (offsets 20 and 24)
        data[at + 20: at + 28] = struct.pack("<II", 64 << 20, 64 << 20)
        at = data.find(b"PK\x01\x02", at + 4)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"forged\.pt is not a checkpoint torch wrote: its \d+ records declare "):
        load_torch_file(path)
    assert TORCH_SIZE_SLACK < 64 << 20


def test_random_bytes_and_empty_files_are_not_checkpoints(tmp_path, capsys):
    random = tmp_path / "random.pt"
    random.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(ValueError, match="random.pt is not a readable checkpoint: neither torch's zip format"):
        load_torch_file(random)
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.pt .*\(it is empty\)"):
        load_checkpoint(tmp_path / "empty.pt")
    line = _one_error_line(["convert", str(random), "--model", "flashocc_tiny",
                            "--out", str(tmp_path / "c.safetensors")], capsys)  # fmt: skip
    assert "random.pt" in line and "weights_only" not in line and len(line) < 300, line


def test_the_legacy_format_reads_and_a_forged_storage_size_is_refused(tmp_path):
    """torch's pre-1.6 format: a pickle stream, then each storage's data. Its storages are allocated from the sizes
    the pickle declares, but only filled from the file, so a forged size costs no memory; it must still end in a
    clean refusal naming the file."""
    path = tmp_path / "legacy.pth"
    torch.save({"a": torch.arange(2.0)}, path, _use_new_zipfile_serialization=False)
    assert torch.equal(load_torch_file(path)["a"], torch.arange(2.0))
    data = path.read_bytes()
    at = data.index(b"cpu") + len(b"cpuq\x06")  # the storage's element count follows its location (memoised)
    assert data[at: at + 2] == b"K\x02"
    path.write_bytes(data[:at] + b"J" + struct.pack("<i", 1 << 30) + data[at + 2:])  # 2 -> 2**30 float32
    with pytest.raises(ValueError, match=r"legacy\.pth is not a readable checkpoint: .*not the size its pickle"):
        load_torch_file(path)


@pytest.mark.parametrize(
    ("tensor", "problem"),
    [
        (torch.zeros(1).expand(1 << 20), r"a \(1048576,\) view of 4\.0 MB over 4 B of saved data"),
        (torch.zeros(3, 3).to_sparse(), "a sparse_coo tensor, not a dense one"),
    ],
)
def test_tensors_that_are_not_plain_saved_data_are_refused(tmp_path, tensor, problem):
    """An expanded view would allocate its full size on first use (a bomb a few bytes long); a sparse or meta tensor
    is no weight."""
    path = tmp_path / "odd.pth"
    torch.save({"state_dict": {"w": tensor}}, path)
    with pytest.raises(ValueError, match=rf"odd\.pth: state_dict\.w is {problem}"):
        load_torch_file(path)


# ----------------------------------------------------------------------------------------------------- U1: pickles
def test_a_refused_pickle_names_the_global_and_not_torchs_advice(tmp_path, capsys):
    path = tmp_path / "system.pt"
    torch.save({"state_dict": {"w": torch.zeros(2)}, "meta": crafting().System()}, path)
    with pytest.raises(ValueError) as refused:
        load_torch_file(path)
    message = str(refused.value)
    assert f"{path} cannot be read as a checkpoint: it pickles posix.system" in message or "nt.system" in message
    assert "weights_only=False" not in message and "\n" not in message and len(message) < 400
    with pytest.raises(ValueError, match=r"it pickles \w+\.system"):
        load_checkpoint(path)
    line = _one_error_line(["eval", "--ckpt", str(path), "--data", str(tmp_path), "--out", str(tmp_path / "e")],
                           capsys)  # fmt: skip
    assert "system.pt" in line and ".system" in line and "weights_only" not in line


# ----------------------------------------------------------------------------------------------------- W5: NaN weights
def test_weights_that_are_not_finite_are_refused_naming_the_keys(tmp_path, capsys):
    state = {"img_backbone.conv1.weight": torch.full((4, 3, 3, 3), float("nan")),
             "img_backbone.bn1.weight": torch.ones(4), "img_backbone.bn1.running_var": torch.tensor([1, 2, 3, np.inf])}
    path = tmp_path / "nan.pth"
    torch.save({"state_dict": state}, path)
    with pytest.raises(ValueError, match=r"nan\.pth: 2 of 3 tensors of its weights hold NaN or infinite values: "
                                         r"img_backbone\.conv1\.weight \(108 of 108 values\), "
                                         r"img_backbone\.bn1\.running_var \(1 of 4 values\)"):  # fmt: skip
        read_checkpoint(path)
    line = _one_error_line(["convert", str(path), "--model", "flashocc_tiny",
                            "--out", str(tmp_path / "c.safetensors")], capsys)  # fmt: skip
    assert "img_backbone.conv1.weight" in line and not (tmp_path / "c.safetensors").exists()
    run = tmp_path / "run.pt"
    torch.save({"format": FORMAT, "model": {"w": torch.zeros(2)}, "ema": {"w": torch.tensor([0.0, -np.inf])}}, run)
    with pytest.raises(ValueError, match=r"run\.pt: 1 of 1 tensors of its 'ema' weights .*w \(1 of 2 values\)"):
        load_checkpoint(run)


# ----------------------------------------------------------------------------------------------------- U2: writing
@pytest.fixture
def tiny_weights(tmp_path) -> Path:
    path = tmp_path / "tiny.pth"
    torch.save(zoo.build("flashocc_tiny").state_dict(), path)
    return path


def test_a_full_disk_is_one_line_naming_the_file_and_leaves_nothing(tiny_weights, tmp_path, monkeypatch, capsys):
    import errno

    import occkit.outputs

    class FullDisk:
        """A file whose writes fail as on a full disk, after creating it (as a real write would)."""

        def __init__(self, path, mode):
            Path(path).write_bytes(b"")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(occkit.outputs, "open", FullDisk, raising=False)
    out = tmp_path / "out" / "tiny.safetensors"
    with pytest.raises(OSError, match=f"no space left on device writing {out}"):
        convert_checkpoint(tiny_weights, "flashocc_tiny", out)
    line = _one_error_line(["convert", str(tiny_weights), "--model", "flashocc_tiny", "--out", str(out)], capsys)
    assert line.endswith(f"no space left on device writing {out}"), line
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []  # no weights, temporary, report


def test_an_unwritable_out_is_one_line_naming_the_file(tiny_weights, tmp_path, monkeypatch, capsys):
    """As root no folder is unwritable, so the refusal is what the rename would raise in one."""

    def refused(source, target):
        raise PermissionError(13, "Permission denied", str(target))

    monkeypatch.setattr(os, "replace", refused)
    out = tmp_path / "tiny.safetensors"
    line = _one_error_line(["convert", str(tiny_weights), "--model", "flashocc_tiny", "--out", str(out)], capsys)
    assert line.endswith(f"cannot write {out}: Permission denied") and "Errno" not in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.pth"]


# ----------------------------------------------------------------------------------------------------- S3: npz files
def _labels(folder: Path, **arrays) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    full = {key: np.zeros(SMALL.shape, np.uint8) for key in ("semantics", "mask_lidar", "mask_camera")}
    np.savez(folder / "labels.npz", **{**full, **arrays})
    return folder / "labels.npz"


def test_an_npz_member_declaring_a_larger_array_is_refused_before_its_data(tmp_path):
    """A 40 MB member (deflated to about 40 KB) whose header declares (8, 8, 600000) uint8 is refused from the
    header, and so is that header in front of 10 bytes (reading the data first would end in an EOF instead); a
    header of the right shape in front of too little data is refused from the zip's declared size."""
    path = tmp_path / "labels.npz"
    masks = {key: np.zeros(SMALL.shape, np.uint8) for key in ("mask_lidar", "mask_camera")}
    np.savez(path, **masks)
    crafting().zip_bomb(path, "semantics.npy", 40 << 20, crafting().npy_header((8, 8, 600_000)), mode="a")
    refused = r"sample t: .*labels\.npz: semantics has shape \(8, 8, 600000\) but expected \(8, 8, 2\)"
    with pytest.raises(LabelError, match=refused):
        read_occ3d_labels(path, "t", SMALL)
    np.savez(path, **masks)
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("semantics.npy", crafting().npy_header((8, 8, 600_000)) + bytes(10))
    with pytest.raises(LabelError, match=refused):
        read_occ3d_labels(path, "t", SMALL)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("semantics.npy", crafting().npy_header(SMALL.shape) + bytes(10))
    with NpzArchive(path, "labels") as archive, pytest.raises(ValueError, match="holds 10 B: the file is truncated"):
        archive.read("semantics")
    np.savez(path, semantics=np.array([{"a": 1}], dtype=object), **masks)  # numpy pickles object arrays
    with pytest.raises(LabelError, match=r"labels\.npz: cannot read labels: semantics holds Python objects"):
        read_occ3d_labels(path, "t", SMALL)


def test_only_the_arrays_asked_for_are_read(tmp_path):
    """A prediction file with an extra member declaring 100 GB still reads: nothing but the grid is opened."""
    path = tmp_path / f"{TOKEN}.npz"
    np.savez(path, semantics=np.ones((200, 200, 16), np.uint8))
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("junk.npy", crafting().npy_header((100_000, 1_000_000)))
    assert read_prediction(path).sum() == 200 * 200 * 16


def test_surroundocc_rows_beyond_the_grid_are_refused_from_the_header(tmp_path):
    path = tmp_path / "rows.npy"
    path.write_bytes(crafting().npy_header((10**9, 4), "<i8"))  # 32 GB declared in 128 bytes
    with pytest.raises(LabelError, match=r"sample s: .*rows\.npy: declares 1000000000 rows, more than the 128 voxels"):
        read_surroundocc_labels(path, "s", SMALL)
    path.write_bytes(crafting().npy_header((100, 4), "<i8") + bytes(80))
    with pytest.raises(LabelError, match=r"holds 80 B: the file is truncated or forged"):
        read_surroundocc_labels(path, "s", SMALL)
    path.write_text("0 0 0 1\n")
    with pytest.raises(LabelError, match=r"rows\.npy: cannot read labels: not a \.npy file"):
        read_surroundocc_labels(path, "s", SMALL)


@pytest.fixture
def eval_tree(tmp_path) -> dict[str, Path]:
    """An Occ3D gts/ tree of two empty frames and a prediction folder with their files."""
    gts, preds = tmp_path / "gts", tmp_path / "preds"
    preds.mkdir()
    tokens = [TOKEN, "1" * 32]
    for token in tokens:
        (gts / "scene-0000" / token).mkdir(parents=True)
        np.savez(gts / "scene-0000" / token / "labels.npz", semantics=np.zeros((200, 200, 16), np.uint8),
                 mask_lidar=np.ones((200, 200, 16), np.uint8), mask_camera=np.ones((200, 200, 16), np.uint8))
        np.savez(preds / f"{token}.npz", semantics=np.zeros((200, 200, 16), np.uint8))
    return {"gts": gts, "preds": preds, "out": tmp_path / "out"}


def test_eval_preds_refuses_a_prediction_bomb_in_one_line(eval_tree, capsys):
    bomb = eval_tree["preds"] / f"{TOKEN}.npz"
    bomb.unlink()
    crafting().zip_bomb(bomb, "semantics.npy", 16 << 20, crafting().npy_header((200, 200, 40_000)))
    with pytest.raises(ValueError, match=rf"{bomb.name}: semantics has shape \(200, 200, 40000\) but occ3d"):
        evaluate_predictions(eval_tree["gts"], eval_tree["preds"])
    line = _one_error_line(["eval-preds", "--gt", str(eval_tree["gts"]), "--preds", str(eval_tree["preds"]),
                            "--out", str(eval_tree["out"])], capsys)  # fmt: skip
    assert bomb.name in line and "(200, 200, 40000)" in line


# ----------------------------------------------------------------------------------------------------- U8: eval-preds
def test_a_link_to_text_is_named_as_not_an_npz_file(eval_tree, tmp_path):
    (tmp_path / "notes.txt").write_text("not an array\n")
    link = eval_tree["preds"] / f"{TOKEN}.npz"
    link.unlink()
    link.symlink_to(tmp_path / "notes.txt")
    with pytest.raises(ValueError, match=rf"{link.name}: cannot read prediction: not a \.npz archive") as refused:
        evaluate_predictions(eval_tree["gts"], eval_tree["preds"])
    assert "pickle" not in str(refused.value)


def test_eval_preds_notes_both_keys_and_extra_files_once(eval_tree, capsys):
    for token in (TOKEN, "1" * 32):
        np.savez(eval_tree["preds"] / f"{token}.npz", semantics=np.zeros((200, 200, 16), np.uint8),
                 pred=np.ones((200, 200, 16), np.uint8))
    for name in ("extra-a", "extra-b", "extra-c"):
        np.savez(eval_tree["preds"] / f"{name}.npz", semantics=np.zeros((200, 200, 16), np.uint8))
    notes: list[str] = []
    result = evaluate_predictions(eval_tree["gts"], eval_tree["preds"], note=notes.append, workers=2)
    # The ground truth is all class 0 (others): semantics (zeros) was scored, not pred (ones).
    assert result["frames"] == 2 and result["per_class_iou"]["others"] == 1.0
    assert len(notes) == 2
    assert notes[0].startswith(f"3 of the 5 files in {eval_tree['preds']} match no ground-truth frame")
    assert "extra-a.npz, extra-b.npz, ..." in notes[0]
    assert notes[1] == f"2 prediction file(s) hold both semantics and pred: semantics was scored (e.g. {TOKEN}.npz)"
    assert main(["eval-preds", "--gt", str(eval_tree["gts"]), "--preds", str(eval_tree["preds"]),
                 "--out", str(eval_tree["out"]), "--workers", "1"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert printed.count("note: ") == 2 and "hold both semantics and pred" in printed


# ----------------------------------------------------------------------------------------------------- W3: flow
def test_flow_faster_than_the_bound_is_refused_in_labels_and_predictions(tmp_path):
    flow = np.zeros((*SMALL.shape, 2), np.float32)
    flow[1, 2, 0] = (3e38, 0.0)
    path = _labels(tmp_path / "gt", flow=flow)
    with pytest.raises(LabelError, match=rf"sample t: .*labels\.npz: flow holds 1 voxels faster than "
                                         rf"{MAX_FLOW_SPEED:g} m/s \(up to 3e\+38 m/s\)"):  # fmt: skip
        read_occ3d_labels(path, "t", SMALL, flow=True)
    flow[1, 2, 0] = (80.0, 80.0)  # each component below the bound, the speed (113 m/s) above it
    path = _labels(tmp_path / "gt", flow=flow)
    with pytest.raises(LabelError, match=r"up to 113 m/s"):
        read_occ3d_labels(path, "t", SMALL, flow=True)
    flow[1, 2, 0] = (60.0, -60.0)
    assert read_occ3d_labels(_labels(tmp_path / "gt", flow=flow), "t", SMALL, flow=True).flow[1, 2, 0, 1] == -60
    prediction = tmp_path / f"{TOKEN}.npz"
    pred_flow = np.zeros((200, 200, 16, 2), np.float32)
    pred_flow[0, 0, 0, 1] = -1e30
    np.savez(prediction, semantics=np.zeros((200, 200, 16), np.uint8), flow=pred_flow)
    with pytest.raises(ValueError, match=rf"{prediction.name}: flow holds 1 voxels faster than 100 m/s"):
        read_prediction_flow(prediction)
