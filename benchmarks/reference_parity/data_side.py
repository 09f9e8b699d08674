"""The data side of the parity test: augmentation matrices and LSS frustums from FlashOcc's own code.

    python benchmarks/reference_parity/data_side.py --reference PATH/TO/FlashOCC \\
        [--out tests/golden/reference_parity/flashocc_data_side.json]

Runs the reference's ``PrepareImageInputs`` (``sample_augmentation`` and ``img_transform``) and
``LoadAnnotationsBEVDepth`` (``sample_bda_augmentation`` and ``bev_transform``) from
``projects/mmdet3d_plugin/datasets/pipelines/loading.py`` of a checkout of Yzichen/FlashOCC at the pinned commit, with
FlashOcc M0's ``data_config`` and ``bda_aug_conf``, on seeded draws, and the frustum of ``LSSViewTransformer``
(``projects/mmdet3d_plugin/models/necks/view_transformer.py``) for M0's, M1's and BEVDet's depth bins; the OpenMMLab
imports and FlashOcc's CUDA ops are stand-ins (:mod:`stand_ins`), as none of them is used by these functions. Writes
each draw's parameters and the reference's ``post_rot`` / ``post_tran`` and BEV ``rot_mat``, and each frustum's axes,
with the repository and commit, for ``tests/test_reference_parity.py`` to compare occkit with.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stand_ins  # noqa: E402 - beside this script

REPOSITORY = "Yzichen/FlashOCC"
#: The commit the goldens come from; another checkout is refused.
PINNED_COMMIT = "4084861d8d605bb01df55fcbc8072036055aa625"
LOADING = "projects/mmdet3d_plugin/datasets/pipelines/loading.py"
VIEW_TRANSFORMER = "projects/mmdet3d_plugin/models/necks/view_transformer.py"
#: grid_config['depth'] of flashocc-r50-M0.py, flashocc-r50.py (M1) and bevdet-r50-cbgs.py.
DEPTH_CONFIGS = {"flashocc_m0": (1.0, 45.0, 1.0), "flashocc_m1": (1.0, 45.0, 0.5), "bevdet_r50_cbgs": (1.0, 60.0, 1.0)}
#: flashocc-r50-M0.py's data_config and bda_aug_conf.
DATA_CONFIG = {"cams": ["CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK",
                        "CAM_BACK_RIGHT"], "Ncams": 6, "input_size": (256, 704), "src_size": (900, 1600),
               "resize": (-0.06, 0.11), "rot": (-5.4, 5.4), "flip": True, "crop_h": (0.0, 0.0), "resize_test": 0.00}
BDA_AUG_CONF = {"rot_lim": (-0.0, 0.0), "scale_lim": (1.0, 1.0), "flip_dx_ratio": 0.5, "flip_dy_ratio": 0.5}
#: BEVDet's wider BEV augmentation (bevdet-r50-cbgs.py), so that rotation and scale are exercised too.
BDA_AUG_CONF_BEVDET = {"rot_lim": (-22.5, 22.5), "scale_lim": (0.95, 1.05), "flip_dx_ratio": 0.5, "flip_dy_ratio": 0.5}


def pinned_checkout(checkout: Path, repository: str, pinned: str) -> str:
    """The commit of ``checkout``, which must be ``repository`` at ``pinned``."""
    done = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{checkout} is not a git checkout of {repository}: {done.stderr.strip()}")
    commit = done.stdout.strip()
    if commit != pinned:
        raise SystemExit(f"{checkout} is at {commit}; the goldens come from {repository} {pinned} (git checkout it)")
    return commit


def load_reference(checkout: Path, relative: str, repository: str = REPOSITORY):
    """The reference's file ``relative`` as a module, imported under its package's name (so that its relative
    imports resolve) with the stand-ins in place."""
    path = checkout / relative
    if not path.is_file():
        raise SystemExit(f"{path} does not exist: --reference must be a checkout of {repository}")
    with stand_ins.installed():
        spec = importlib.util.spec_from_file_location(relative.removesuffix(".py").replace("/", "."), path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module


def frustums(view_transformer) -> dict:
    """The reference frustum ``(D, fH, fW, 3)`` of each depth config at M0's input (256 x 704, stride 16), as its
    three axes; that the axes rebuild it exactly is checked here."""
    height, width = DATA_CONFIG["input_size"]
    found = {}
    for name, depth in DEPTH_CONFIGS.items():
        grid = {"x": [-40, 40, 0.4], "y": [-40, 40, 0.4], "z": [-1, 5.4, 6.4], "depth": list(depth)}
        frustum = view_transformer.LSSViewTransformer(grid, (height, width), downsample=16, in_channels=8,
                                                      out_channels=4).frustum  # fmt: skip
        u, v, d = frustum[0, 0, :, 0], frustum[0, :, 0, 1], frustum[:, 0, 0, 2]
        rebuilt = torch.stack(torch.broadcast_tensors(u[None, None, :], v[None, :, None], d[:, None, None]), dim=-1)
        assert torch.equal(rebuilt, frustum), name
        found[name] = {"depth": list(depth), "image_size": [height, width], "stride": 16,
                       "shape": list(frustum.shape), "u": u.tolist(), "v": v.tolist(), "d": d.tolist()}
    return found


def image_draws(loading, count: int) -> list[dict]:
    """``count`` training draws (seeds 0..count-1) and the test-time transform, with the reference's matrices."""
    height, width = DATA_CONFIG["src_size"]
    image = Image.new("RGB", (width, height))
    draws = []
    for seed in [*range(count), None]:
        prepare = loading.PrepareImageInputs(DATA_CONFIG, is_train=seed is not None)
        if seed is not None:
            np.random.seed(seed)
        resize, resize_dims, crop, flip, rotate = prepare.sample_augmentation(H=height, W=width)
        _, post_rot, post_tran = prepare.img_transform(image, torch.eye(2), torch.zeros(2), resize=resize,
                                                       resize_dims=resize_dims, crop=crop, flip=flip, rotate=rotate)
        draws.append({"seed": seed, "train": seed is not None, "resize": float(resize),
                      "resize_dims": [int(v) for v in resize_dims], "crop": [int(v) for v in crop],
                      "flip": bool(flip), "rotate_deg": float(rotate), "post_rot": post_rot.tolist(),
                      "post_tran": post_tran.tolist()})
    return draws


def bev_draws(loading, config: dict, count: int) -> list[dict]:
    """``count`` seeded BEV augmentation draws of ``config`` with the reference's ``rot_mat``."""
    draws = []
    for seed in range(count):
        annotations = loading.LoadAnnotationsBEVDepth(config, classes=[], is_train=True)
        np.random.seed(seed)
        rotate, scale, flip_dx, flip_dy = annotations.sample_bda_augmentation()
        _, rot_mat = annotations.bev_transform(torch.zeros(0, 9), rotate, scale, flip_dx, flip_dy)
        draws.append({"seed": seed, "rotate_deg": float(rotate), "scale": float(scale), "flip_dx": bool(flip_dx),
                      "flip_dy": bool(flip_dy), "rot_mat": rot_mat.tolist()})
    return draws


def harness_arguments(description: str, repository: str, pinned: str, golden: str) -> tuple[argparse.Namespace, str]:
    """The command line every harness script takes (``--reference``, ``--out``, ``--draws``) and the checkout's
    commit, which must be ``pinned``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--reference", type=Path, required=True, help=f"a checkout of {repository}")
    parser.add_argument("--out", type=Path, default=Path("tests/golden/reference_parity") / golden)
    parser.add_argument("--draws", type=int, default=16, help="seeded draws per augmentation (default 16)")
    args = parser.parse_args()
    return args, pinned_checkout(args.reference, repository, pinned)


def write_golden(path: Path, golden: dict, what: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(golden, indent=1) + "\n")
    print(f"wrote {what} of {golden['repository']}@{golden['commit'][:12]} to {path}")


def main() -> int:
    args, commit = harness_arguments(__doc__.splitlines()[0], REPOSITORY, PINNED_COMMIT, "flashocc_data_side.json")
    loading = load_reference(args.reference, LOADING)
    golden = {
        "repository": REPOSITORY, "commit": commit, "files": [LOADING, VIEW_TRANSFORMER],
        "data_config": DATA_CONFIG, "bda_aug_conf": BDA_AUG_CONF, "bda_aug_conf_bevdet": BDA_AUG_CONF_BEVDET,
        "image": image_draws(loading, args.draws),
        "bev": bev_draws(loading, BDA_AUG_CONF, args.draws),
        "bev_bevdet": bev_draws(loading, BDA_AUG_CONF_BEVDET, args.draws),
        "frustum": frustums(load_reference(args.reference, VIEW_TRANSFORMER)),
    }  # fmt: skip
    write_golden(args.out, golden, f"{len(golden['image'])} image and {2 * args.draws} BEV draws and "
                                   f"{len(golden['frustum'])} frustums")
    return 0


if __name__ == "__main__":
    sys.exit(main())
