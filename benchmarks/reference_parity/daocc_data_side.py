"""The data side of the parity test for DAOcc: its image augmentation and BEV flips, from DAOcc's own code.

    python benchmarks/reference_parity/daocc_data_side.py --reference PATH/TO/DAOcc \\
        [--out tests/golden/reference_parity/daocc_data_side.json]

Runs ``ImageAug3D`` (``sample_augmentation`` and ``img_transform``) and ``RandomFlip3D`` of
``mmdet3d/datasets/pipelines/transforms_3d.py`` of a checkout of AlphaPlusTT/DAOcc at the pinned commit, with the
settings of its ``configs/nuscenes/default.yaml`` (which ``daocc_occ3d_nus_w_mask.yaml`` inherits; its
``GlobalRotScaleTrans`` is the identity there: scale 1, rotation 0, translation 0), on seeded draws. The imports of
that file are stand-ins (:mod:`stand_ins`), none of them used by these functions.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from data_side import harness_arguments, load_reference, write_golden  # noqa: E402 - beside this script

REPOSITORY = "AlphaPlusTT/DAOcc"
PINNED_COMMIT = "6846432bbc1eff9d2a601900d21f1031df170a8c"
TRANSFORMS = "mmdet3d/datasets/pipelines/transforms_3d.py"
#: configs/nuscenes/default.yaml: image_size, augment2d.resize[2], augment2d.rotate; nuScenes' 1600 x 900 images.
IMAGE_AUG = {"final_dim": (256, 704), "resize_lim": (-0.06, 0.11), "bot_pct_lim": (0.0, 0.0), "rot_lim": (-5.4, 5.4),
             "rand_flip": True}
ORIGINAL_SIZE = (1600, 900)


def image_draws(transforms, count: int) -> list[dict]:
    """``count`` training draws (seeds 0..count-1) and the test-time transform, with the reference's 4 x 4 matrix."""
    image = Image.new("RGB", ORIGINAL_SIZE)
    draws = []
    for seed in [*range(count), None]:
        train = seed is not None
        settings = IMAGE_AUG if train else {**IMAGE_AUG, "rot_lim": (0.0, 0.0), "rand_flip": False}
        augment = transforms.ImageAug3D(**settings, is_train=train)
        if train:
            np.random.seed(seed)
        resize, resize_dims, crop, flip, rotate = augment.sample_augmentation({"ori_shape": ORIGINAL_SIZE})
        _, rotation, translation = augment.img_transform(image, torch.eye(2), torch.zeros(2), resize=resize,
                                                         resize_dims=resize_dims, crop=crop, flip=flip, rotate=rotate)
        draws.append({"seed": seed, "train": train, "resize": float(resize), "crop": [int(v) for v in crop],
                      "flip": bool(flip), "rotate_deg": float(rotate), "rotation": rotation.tolist(),
                      "translation": translation.tolist()})
    return draws


def flip_draws(transforms, count: int) -> list[dict]:
    """``count`` seeded ``RandomFlip3D`` draws: which flips, and the LiDAR and occupancy matrices they give."""
    draws = []
    for seed in range(count):
        np.random.seed(seed)
        data = transforms.RandomFlip3D()({"lidar_aug_matrix": np.eye(4), "occ_aug_matrix": np.eye(4)})
        lidar, occupancy = data["lidar_aug_matrix"], data["occ_aug_matrix"]
        draws.append({"seed": seed, "flip_y": bool(lidar[1, 1] < 0), "flip_x": bool(lidar[0, 0] < 0),
                      "lidar_aug_matrix": lidar.tolist(), "occ_aug_matrix": occupancy.tolist()})
    return draws


def main() -> int:
    args, commit = harness_arguments(__doc__.splitlines()[0], REPOSITORY, PINNED_COMMIT, "daocc_data_side.json")
    transforms = load_reference(args.reference, TRANSFORMS, REPOSITORY)
    golden = {"repository": REPOSITORY, "commit": commit, "files": [TRANSFORMS], "image_aug": IMAGE_AUG,
              "original_size": ORIGINAL_SIZE, "image": image_draws(transforms, args.draws),
              "flip": flip_draws(transforms, args.draws)}  # fmt: skip
    write_golden(args.out, golden, f"{len(golden['image'])} image and {args.draws} flip draws")
    return 0


if __name__ == "__main__":
    sys.exit(main())
