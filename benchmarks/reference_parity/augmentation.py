"""Golden augmentation matrices from FlashOcc's own pipeline code, for the data side of the parity test.

    python benchmarks/reference_parity/augmentation.py --reference PATH/TO/FlashOCC \\
        [--out tests/golden/reference_parity/flashocc_augmentation.json]

Runs the reference's ``PrepareImageInputs`` (``sample_augmentation`` and ``img_transform``) and
``LoadAnnotationsBEVDepth`` (``sample_bda_augmentation`` and ``bev_transform``) from
``projects/mmdet3d_plugin/datasets/pipelines/loading.py`` of a checkout of Yzichen/FlashOCC at the pinned commit, with
FlashOcc M0's ``data_config`` and ``bda_aug_conf``, on seeded draws; the OpenMMLab imports are stand-ins
(:mod:`stand_ins`), as none of them is used by these functions. Writes each draw's parameters and the reference's
``post_rot`` / ``post_tran`` and BEV ``rot_mat``, with the repository and commit, for
``tests/test_reference_parity.py`` to compare occkit's ``image_aug_matrix`` and ``sample_bev_aug`` with.
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
#: flashocc-r50-M0.py's data_config and bda_aug_conf.
DATA_CONFIG = {"cams": ["CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK",
                        "CAM_BACK_RIGHT"], "Ncams": 6, "input_size": (256, 704), "src_size": (900, 1600),
               "resize": (-0.06, 0.11), "rot": (-5.4, 5.4), "flip": True, "crop_h": (0.0, 0.0), "resize_test": 0.00}
BDA_AUG_CONF = {"rot_lim": (-0.0, 0.0), "scale_lim": (1.0, 1.0), "flip_dx_ratio": 0.5, "flip_dy_ratio": 0.5}
#: BEVDet's wider BEV augmentation (bevdet-r50-cbgs.py), so that rotation and scale are exercised too.
BDA_AUG_CONF_BEVDET = {"rot_lim": (-22.5, 22.5), "scale_lim": (0.95, 1.05), "flip_dx_ratio": 0.5, "flip_dy_ratio": 0.5}


def commit_of(checkout: Path) -> str:
    done = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{checkout} is not a git checkout of {REPOSITORY}: {done.stderr.strip()}")
    return done.stdout.strip()


def load_reference(checkout: Path):
    """The reference's ``loading.py`` as a module, imported with the stand-ins in place."""
    path = checkout / LOADING
    if not path.is_file():
        raise SystemExit(f"{path} does not exist: --reference must be a checkout of {REPOSITORY}")
    with stand_ins.installed():
        spec = importlib.util.spec_from_file_location("reference_loading", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module


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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, required=True, help=f"a checkout of {REPOSITORY}")
    parser.add_argument("--out", type=Path, default=Path("tests/golden/reference_parity/flashocc_augmentation.json"))
    parser.add_argument("--draws", type=int, default=16)
    args = parser.parse_args()
    commit = commit_of(args.reference)
    if commit != PINNED_COMMIT:
        raise SystemExit(f"{args.reference} is at {commit}; the goldens come from {PINNED_COMMIT} (git checkout it)")
    loading = load_reference(args.reference)
    golden = {
        "repository": REPOSITORY, "commit": commit, "file": LOADING,
        "data_config": DATA_CONFIG, "bda_aug_conf": BDA_AUG_CONF, "bda_aug_conf_bevdet": BDA_AUG_CONF_BEVDET,
        "image": image_draws(loading, args.draws),
        "bev": bev_draws(loading, BDA_AUG_CONF, args.draws),
        "bev_bevdet": bev_draws(loading, BDA_AUG_CONF_BEVDET, args.draws),
    }  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(golden, indent=1) + "\n")
    print(f"wrote {len(golden['image'])} image and {2 * args.draws} BEV draws of {REPOSITORY}@{commit[:12]} to "
          f"{args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
