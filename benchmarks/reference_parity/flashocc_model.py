"""The model side of the parity test for FlashOcc: the reference's state-dict keys and its outputs on fixed inputs.

    PYTHONPATH=MMSITE python benchmarks/reference_parity/flashocc_model.py --reference PATH/TO/FlashOCC

``MMSITE`` holds mmcv 1.7.2 (built with ``MMCV_WITH_OPS=0``) and mmdet 2.28.2 (docs/reproducing.md). The script
builds ``BEVDetOCC`` from the reference's own config files (``projects/configs/flashocc/flashocc-r50-M0.py`` for M0,
``flashocc-r50.py`` for M1, whose ``model`` dicts it reads; their ``_base_`` files hold only dataset and runtime
settings), with the reference's own modules, mmdet's ``ResNet`` and mmcv's ``ConvModule``, and:

* **paper size**: writes the full state dict's keys and shapes to ``docs/results/parity/flashocc_m{0,1}.json``;
* **reduced width**: the same config with narrow channels (:data:`REDUCED`), random weights (:func:`randomise`) and
  one fixed batch (:func:`fixed_inputs`), run in eval mode through ``BEVDetOCC.extract_feat`` and
  ``forward_occ_train``; writes the reference state dict as an mmcv checkpoint, the inputs, the output of each stage
  (:data:`STAGES`) and the occupancy loss to ``tests/golden/reference_parity/flashocc_model/``.

Stand-ins (:mod:`openmmlab`, :mod:`flashocc_ops`): mmcv's compiled ops, mmdet3d's registries and ``CenterPoint``
base, and BEVPoolv2 in PyTorch. Every file written is byte-reproducible from the same checkout.
"""

from __future__ import annotations

import ast
import copy
import hashlib
import importlib
import io
import json
import sys
import types
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import flashocc_ops  # noqa: E402 - beside this script
import openmmlab  # noqa: E402
from data_side import PINNED_COMMIT, REPOSITORY, pinned_checkout  # noqa: E402

CONFIGS = {"flashocc_m0": "projects/configs/flashocc/flashocc-r50-M0.py",
           "flashocc_m1": "projects/configs/flashocc/flashocc-r50.py"}  # fmt: skip
PLUGIN = "projects/mmdet3d_plugin"
#: The plugin's modules that define what BEVDetOCC is built from (importing one registers its classes).
MODULES = ("models.backbones.resnet", "models.necks.fpn", "models.necks.lss_fpn", "models.necks.view_transformer",
           "models.losses.cross_entropy_loss", "models.dense_heads.bev_occ_head", "models.detectors.bevdet_occ")

#: The reduced-width model: the paper configs with every width divided by 16 (the image backbone through mmdet's
#: ``base_channels``), a 16 x 16 BEV of 1.6 m cells, and 64 x 192 images (sides divisible by the stride 32, as the
#: paper's); the goldens of both models then take 3 MB.
REDUCED = {
    "input_size": (64, 192),
    "grid_xy": [-12.8, 12.8, 1.6],
    "base_channels": 4,
    "image_neck_channels": 16,
    "context_channels": 4,
    "bev_neck_channels": {"flashocc_m0": 8, "flashocc_m1": 16},
}
CAMERAS = 6
#: Stage name -> what it is in the reference (shape and axes as the reference holds it).
STAGES = {
    "image_features": "img_neck output, (B*N, C, fH, fW)",
    "depth": "img_view_transformer depth, softmax over bins, (B*N, D, fH, fW)",
    "bev": "img_view_transformer BEV, (B, C, Dy, Dx)",
    "bev_encoded": "bev_encoder (CustomResNet + FPN_LSS) output, (B, C, Dy, Dx)",
    "logits": "occ_head output, (B, Dx, Dy, Dz, classes)",
}
GOLDEN = Path("tests/golden/reference_parity/flashocc_model")
KEYS = Path("docs/results/parity")


def model_config(checkout: Path, relative: str) -> dict:
    """The ``model`` dict of a reference config file, evaluated without its ``_base_`` list."""
    tree = ast.parse((checkout / relative).read_text(), relative)
    tree.body = [node for node in tree.body
                 if not (isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "_base_" for t in node.targets))]
    namespace: dict = {}
    exec(compile(tree, relative, "exec"), namespace)  # noqa: S102 - the reference's own config, as mmcv runs it
    return copy.deepcopy(namespace["model"])


def reduced(model: dict, name: str) -> dict:
    """``model`` with :data:`REDUCED`'s widths, grid and image size; everything else as the paper's config."""
    model = copy.deepcopy(model)
    context, neck = REDUCED["context_channels"], REDUCED["bev_neck_channels"][name]
    base = REDUCED["base_channels"]
    model["img_backbone"].update(base_channels=base, pretrained=None, with_cp=False)
    model["img_neck"].update(in_channels=[base * 16, base * 32], out_channels=REDUCED["image_neck_channels"])
    view = model["img_view_transformer"]
    view.update(input_size=REDUCED["input_size"], in_channels=REDUCED["image_neck_channels"], out_channels=context)
    view["grid_config"] = dict(view["grid_config"], x=list(REDUCED["grid_xy"]), y=list(REDUCED["grid_xy"]))
    model["img_bev_encoder_backbone"].update(numC_input=context, num_channels=[context * 2, context * 4, context * 8])
    model["img_bev_encoder_neck"].update(in_channels=context * 8 + context * 2, out_channels=neck)
    model["occ_head"].update(in_dim=neck, out_dim=neck)
    return model


def import_plugin(checkout: Path) -> types.ModuleType:
    """The plugin's model modules imported (classes registered); returns ``bevdet_occ``. The plugin's packages are
    entered without their ``__init__`` files, which import models the harness does not build."""
    for package in ("projects", "projects.mmdet3d_plugin", "projects.mmdet3d_plugin.models",
                    *(f"projects.mmdet3d_plugin.models.{p}" for p in ("backbones", "necks", "dense_heads",
                                                                      "detectors", "losses"))):  # fmt: skip
        module = types.ModuleType(package)
        module.__path__ = [str(checkout / package.replace(".", "/"))]
        sys.modules[package] = module
    modules = [importlib.import_module(f"projects.mmdet3d_plugin.{name}") for name in MODULES]
    return modules[-1]


def build(model: dict) -> torch.nn.Module:
    from mmdet.models.builder import MODELS

    return MODELS.build(copy.deepcopy(model))


def randomise(model: torch.nn.Module, seed: int) -> None:
    """Deterministic weights of unit scale everywhere (nothing left at a trivial 0 or 1): convolution and linear
    weights ~ N(0, 1 / fan_in), biases ~ U(-0.1, 0.1), BatchNorm weights ~ U(0.5, 1.5), running means ~
    U(-0.1, 0.1) and variances ~ U(0.5, 1.5)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for module in model.modules():
            tensors = [*module.named_parameters(recurse=False), *module.named_buffers(recurse=False)]
            for name, tensor in tensors:
                if tensor.dtype not in (torch.float32, torch.float64):
                    continue
                uniform = torch.rand(tensor.shape, generator=generator)
                if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                    low, high = (-0.1, 0.1) if name in ("bias", "running_mean") else (0.5, 1.5)
                    tensor.copy_(low + (high - low) * uniform)
                elif tensor.dim() > 1:
                    fan_in = tensor[0].numel()
                    tensor.copy_(torch.randn(tensor.shape, generator=generator) / fan_in**0.5)
                else:
                    tensor.copy_(-0.1 + 0.2 * uniform)


def rotation_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def fixed_inputs(seed: int = 0) -> dict[str, np.ndarray]:
    """One batch of six cameras around the ego (nuScenes-like extrinsics and 1600 x 900 intrinsics), each image
    augmented by its own resize, crop, flip and rotation to 64 x 192 (``post_rots``, ``post_trans``), a BEV
    augmentation with both flips (``bda``), the images' pixels, and an occupancy target and camera mask on the
    reduced grid."""
    rng = np.random.default_rng(seed)
    height, width = REDUCED["input_size"]
    cam_to_ego, intrinsics, post_rots, post_trans = [], [], [], []
    for index in range(CAMERAS):
        yaw = np.deg2rad(60.0 * index) + rng.uniform(-0.05, 0.05)
        # camera (x right, y down, z forward) -> ego (x forward, y left, z up), then turned by the camera's yaw
        axes = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
        pose = np.eye(4)
        pose[:3, :3] = rotation_z(yaw) @ axes
        pose[:3, 3] = [1.5 * np.cos(yaw), 0.9 * np.sin(yaw), 1.6 + rng.uniform(-0.05, 0.05)]
        cam_to_ego.append(pose)
        focal = rng.uniform(1150.0, 1270.0)
        intrinsics.append(np.array([[focal, 0.0, 800.0 + rng.uniform(-20, 20)],
                                    [0.0, focal, 450.0 + rng.uniform(-20, 20)], [0.0, 0.0, 1.0]]))  # fmt: skip
        # BEVDet's img_transform: resize, crop, optional horizontal flip, rotation about the crop's centre.
        resize = width / 1600.0 * rng.uniform(1.0, 1.1)
        crop = np.array([rng.uniform(0, 1600 * resize - width), rng.uniform(0, 900 * resize - height)])
        rotation = np.zeros((2, 2))
        rotation[:] = np.eye(2) * resize
        translation = -crop
        if index % 2:
            flip = np.array([[-1.0, 0.0], [0.0, 1.0]])
            rotation, translation = flip @ rotation, flip @ translation + np.array([width, 0.0])
        angle = np.deg2rad(rng.uniform(-5.4, 5.4))
        turn = np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])
        centre = np.array([width, height]) / 2
        rotation, translation = turn @ rotation, turn @ (translation - centre) + centre
        rot3, tran3 = np.eye(3), np.zeros(3)
        rot3[:2, :2], tran3[:2] = rotation, translation
        post_rots.append(rot3)
        post_trans.append(tran3)
    bda = rotation_z(np.deg2rad(10.0)) @ np.diag([-1.0, -1.0, 1.0])
    grid = int(round((REDUCED["grid_xy"][1] - REDUCED["grid_xy"][0]) / REDUCED["grid_xy"][2]))
    ego_to_global = np.eye(4)
    ego_to_global[:3, :3], ego_to_global[:3, 3] = rotation_z(0.7), [600.0, 1600.0, 0.0]
    return {
        "images": rng.standard_normal((1, CAMERAS, 3, height, width)).astype(np.float32),
        "sensor2egos": np.stack(cam_to_ego)[None].astype(np.float32),
        "ego2globals": np.repeat(ego_to_global[None, None], CAMERAS, axis=1).astype(np.float32),
        "intrins": np.stack(intrinsics)[None].astype(np.float32),
        "post_rots": np.stack(post_rots)[None].astype(np.float32),
        "post_trans": np.stack(post_trans)[None].astype(np.float32),
        "bda": bda[None].astype(np.float32),
        "voxel_semantics": rng.integers(0, 18, (1, grid, grid, 16)).astype(np.uint8),
        "mask_camera": (rng.random((1, grid, grid, 16)) < 0.5).astype(np.uint8),
    }


def run(model: torch.nn.Module, inputs: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Each stage's output and the occupancy loss, in eval mode, through the detector's own methods."""
    tensors = {name: torch.from_numpy(value) for name, value in inputs.items()}
    captured: dict[str, torch.Tensor] = {}

    def keep(name, pick=lambda output: output):
        return lambda module, args, output: captured.__setitem__(name, pick(output).detach().clone())

    hooks = [model.img_neck.register_forward_hook(keep("image_features", lambda out: out[0])),
             model.img_view_transformer.register_forward_hook(keep("bev", lambda out: out[0])),
             model.img_view_transformer.register_forward_hook(keep("depth", lambda out: out[1])),
             model.img_bev_encoder_neck.register_forward_hook(keep("bev_encoded")),
             model.occ_head.register_forward_hook(keep("logits"))]  # fmt: skip
    model.eval()
    with torch.no_grad():
        img_inputs = [tensors[name] for name in ("images", "sensor2egos", "ego2globals", "intrins", "post_rots",
                                                 "post_trans", "bda")]  # fmt: skip
        img_feats, _, _ = model.extract_feat(None, img_inputs=img_inputs, img_metas=None)
        losses = model.forward_occ_train(img_feats[0], tensors["voxel_semantics"], tensors["mask_camera"])
    for hook in hooks:
        hook.remove()
    return {name: captured[name].numpy() for name in STAGES}, {name: float(value) for name, value in losses.items()}


def key_list(model: torch.nn.Module, name: str, config: str, commit: str) -> dict:
    return {"reference": {"repository": REPOSITORY, "commit": commit, "config": config, "model": name},
            "keys": {key: list(value.shape) for key, value in model.state_dict().items()}}  # fmt: skip


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An uncompressed ``.npz`` of ``arrays`` in their order, with fixed member timestamps (byte-reproducible)."""
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
            archive.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), member.getvalue())
    return buffer.getvalue()


def checkpoint_bytes(model: torch.nn.Module, meta: dict) -> bytes:
    """The reference state dict as an mmcv checkpoint (``{"state_dict", "meta"}``), saved by ``torch.save``."""
    buffer = io.BytesIO()
    state = {key: value.detach().clone().contiguous() for key, value in model.state_dict().items()}
    torch.save({"meta": meta, "state_dict": state}, buffer)
    return buffer.getvalue()


def write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    print(f"wrote {path} ({len(data) / 1e6:.2f} MB, sha256 {hashlib.sha256(data).hexdigest()[:12]})")


def main() -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, required=True, help=f"a checkout of {REPOSITORY}")
    parser.add_argument("--golden", type=Path, default=GOLDEN, help=f"golden folder (default {GOLDEN})")
    parser.add_argument("--keys", type=Path, default=KEYS, help=f"key-list folder (default {KEYS})")
    args = parser.parse_args()
    commit = pinned_checkout(args.reference, REPOSITORY, PINNED_COMMIT)
    torch.use_deterministic_algorithms(True)
    torch.set_num_threads(1)  # one summation order for the reductions
    with openmmlab.installed({"projects.mmdet3d_plugin.ops": flashocc_ops.module(openmmlab.placeholder)}):
        import_plugin(args.reference)
        inputs = fixed_inputs()
        meta = {"repository": REPOSITORY, "commit": commit, "reduced": REDUCED, "stages": STAGES,
                "command": "PYTHONPATH=MMSITE python benchmarks/reference_parity/flashocc_model.py --reference DIR",
                "models": {}}  # fmt: skip
        for seed, (name, config) in enumerate(CONFIGS.items()):
            paper = model_config(args.reference, config)
            write(args.keys / f"{name}.json",
                  (json.dumps(key_list(build(paper), name, config, commit), indent=1) + "\n").encode())
            model_cfg = reduced(paper, name)
            torch.manual_seed(seed)
            model = build(model_cfg)
            randomise(model, seed)
            stages, losses = run(model, inputs)
            write(args.golden / f"{name}.pth", checkpoint_bytes(model, {"repository": REPOSITORY, "commit": commit,
                                                                        "config": config, "model": name}))  # fmt: skip
            write(args.golden / f"{name}_stages.npz", npz_bytes(stages))
            shapes = {stage: list(array.shape) for stage, array in stages.items()}
            meta["models"][name] = {"config": config, "model": model_cfg, "losses": losses, "shapes": shapes}
        write(args.golden / "inputs.npz", npz_bytes(inputs))
        write(args.golden / "meta.json", (json.dumps(meta, indent=1, default=list) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
