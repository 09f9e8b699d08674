"""Inference networks for one fixed rig: a zoo model with everything that depends only on calibration precomputed.

A deployed occupancy model sees one vehicle: its cameras, their intrinsics and mounting, the LiDAR mounting, no
augmentation. Every index and sampling tensor derived from those alone is computed once here, from a reference
batch, and kept as a buffer, so an exported graph holds it as a constant:

* FlashOcc: the LSS pooling plan (``ranks_depth``, ``ranks_feat``, ``ranks_bev``);
* DA-Occ: both pooling plans (200 x 200 BEV and 32 x 32 x 16 height volume), each frustum point's height bin and
  the 27 camera parameters of the camera-aware depth and height nets;
* DAOcc: the projection sampling plan (``grid_sample`` coordinates, target voxel rows, camera weights) and the BVRE
  sampling grid.

What changes every frame is the input: camera images, and for DAOcc the voxelized LiDAR sweep with the rulebooks of
its sparse convolutions (:mod:`occkit.models.sparse_rules`), which :meth:`DeployedNetwork.inputs` computes outside
the network. The contract: a new calibration (another vehicle, a re-calibrated camera, another set of working
cameras in ``camera_mask``) needs a new network; the batch size is the reference batch's.

The networks compute exactly what the model's ``forward`` computes in eval mode for the reference batch's rig
(detection head left out); ``occkit.export`` checks that against the model itself.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.models.da_occ import DirectionAwareOcc
from occkit.models.daocc import DAOcc
from occkit.models.flashocc import FlashOcc
from occkit.models.heads.depth import camera_parameters
from occkit.models.sparse_rules import RulebookSparseEncoder
from occkit.models.view_transform.lss import PoolingPlan, fold_height, gather_point_weights, voxel_pool
from occkit.types import Batch

__all__ = ["OUTPUT_NAME", "DeployedNetwork", "DeployedFlashOcc", "DeployedDirectionAwareOcc", "DeployedDAOcc",
           "deploy"]

#: Name of the single output, occupancy logits ``(B, K, X, Y, Z)``.
OUTPUT_NAME = "occupancy_logits"


class DeployedNetwork(nn.Module):
    """``forward(*inputs) -> (B, K, X, Y, Z)`` occupancy logits, inputs in the order of :attr:`input_names`.

    Subclasses set the three attributes below and implement :meth:`inputs` and :meth:`logits`.
    """

    input_names: list[str]
    """Names of the forward arguments, in order."""
    input_docs: dict[str, str]
    """Input name -> what it holds, with its shape."""
    dynamic_axes: dict[str, dict[int, str]]
    """Input name -> {axis: name} of the axes whose size changes from frame to frame."""

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        """The network's inputs for a batch of the same rig, by name, in :attr:`input_names` order."""
        raise NotImplementedError

    def logits(self, inputs: dict[str, Tensor]) -> Tensor:
        """Occupancy logits ``(B, K, X, Y, Z)`` from the named inputs."""
        raise NotImplementedError

    def forward(self, *inputs: Tensor) -> Tensor:
        if len(inputs) != len(self.input_names):
            raise ValueError(f"expected {len(self.input_names)} inputs ({', '.join(self.input_names)}), "
                             f"got {len(inputs)}")
        return self.logits(dict(zip(self.input_names, inputs, strict=True)))

    def _check_images(self, images: Tensor | None, shape: tuple[int, ...]) -> Tensor:
        if images is None or tuple(images.shape[:2]) != shape[:2] or tuple(images.shape[-2:]) != shape[-2:]:
            got = None if images is None else tuple(images.shape)
            raise ValueError(f"the network was made for images of shape {shape}, got {got}")
        return images


def _buffers(module: nn.Module, **tensors: Tensor) -> None:
    """Register calibration constants as non-persistent buffers: they follow ``.to(device)`` but stay out of
    state dicts (they are derived, not learned)."""
    for name, tensor in tensors.items():
        module.register_buffer(name, tensor.detach().clone(), persistent=False)


class DeployedFlashOcc(DeployedNetwork):
    """FlashOcc with a fixed LSS pooling plan. Input ``images (B, N, 3, H, W)``."""

    def __init__(self, model: FlashOcc, batch: Batch) -> None:
        super().__init__()
        self.model = model
        self.image_shape = tuple(batch.images.shape)
        plan = model.view_transform.plan(batch.intrinsics, batch.cam2ego, batch.img_aug, batch.occ_aug,
                                         image_size=tuple(batch.images.shape[-2:]), camera_mask=batch.camera_mask)
        _buffers(self, ranks_depth=plan.ranks_depth, ranks_feat=plan.ranks_feat, ranks_bev=plan.ranks_bev)
        self.point_shape, self.grid_shape = plan.point_shape, plan.grid_shape
        self.input_names = ["images"]
        self.input_docs = {"images": f"{self.image_shape} float32 normalised camera images (test transform)"}
        self.dynamic_axes = {}

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        return {"images": self._check_images(batch.images, self.image_shape)}

    def logits(self, inputs: dict[str, Tensor]) -> Tensor:
        model = self.model
        plan = PoolingPlan(self.ranks_depth, self.ranks_feat, self.ranks_bev, self.point_shape, self.grid_shape)
        bev, _ = model.view_transform(model.image_encoder(inputs["images"]), plan)  # (B, C, X, Y)
        return model.occupancy_head(model.bev_encoder(bev))


class DeployedDirectionAwareOcc(DeployedNetwork):
    """DA-Occ with fixed pooling plans, height bins and camera parameters. Input ``images (B, N, 3, H, W)``."""

    def __init__(self, model: DirectionAwareOcc, batch: Batch) -> None:
        super().__init__()
        self.model = model
        self.image_shape = tuple(batch.images.shape)
        # The model's own geometry (the cached plans with fixed_calibration), so both compute the same thing.
        z_bins, bev_plan, height_plan = model._geometry(batch)
        cameras = camera_parameters(batch.intrinsics, batch.img_aug, batch.occ_aug, batch.cam2ego)
        _buffers(self, camera_params=cameras, z_bins=z_bins,
                 bev_depth=bev_plan.ranks_depth, bev_feat=bev_plan.ranks_feat, bev_rows=bev_plan.ranks_bev,
                 height_depth=height_plan.ranks_depth, height_feat=height_plan.ranks_feat,
                 height_rows=height_plan.ranks_bev)  # fmt: skip
        self.plan_shapes = {"bev": (bev_plan.point_shape, bev_plan.grid_shape),
                            "height": (height_plan.point_shape, height_plan.grid_shape)}  # fmt: skip
        self.input_names = ["images"]
        self.input_docs = {"images": f"{self.image_shape} float32 normalised camera images (test transform)"}
        self.dynamic_axes = {}

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        return {"images": self._check_images(batch.images, self.image_shape)}

    def logits(self, inputs: dict[str, Tensor]) -> Tensor:
        """DA-Occ's forward (``DirectionAwareOcc.forward``) with the calibration-only tensors taken from buffers."""
        model = self.model
        features = model.image_encoder(inputs["images"])  # (B, N, C, h, w)
        batch_size, cameras = features.shape[:2]
        flat = features.flatten(0, 1)
        depth_logits, context = model.depth_net(flat, self.camera_params)
        height_logits, _ = model.height_net(flat, self.camera_params)
        depth = depth_logits.softmax(dim=1).unflatten(0, (batch_size, cameras))  # (B, N, D, h, w)
        height = height_logits.softmax(dim=1).unflatten(0, (batch_size, cameras))  # (B, N, Z, h, w)
        context = context.unflatten(0, (batch_size, cameras))  # (B, N, C, h, w)
        bev_plan = PoolingPlan(self.bev_depth, self.bev_feat, self.bev_rows, *self.plan_shapes["bev"])
        height_plan = PoolingPlan(self.height_depth, self.height_feat, self.height_rows, *self.plan_shapes["height"])

        bev = model.bev_encoder(fold_height(voxel_pool(depth, context, bev_plan)))  # (B, C, X, Y)
        bev = model.bev_horizontal(bev) + model.bev_vertical(bev)
        volume = voxel_pool(gather_point_weights(height, self.z_bins), context, height_plan)  # (B, C, Z, X, Y)
        c, z, x, y = volume.shape[1:]
        sliced = model.height_vertical(volume.reshape(batch_size, c, z, x * y))  # (B, C, Z, X*Y)
        folded = sliced.reshape(batch_size, c, z, x, y).transpose(1, 2).reshape(batch_size, z * c, x, y)
        heights = F.interpolate(model.height_reduce(folded), size=bev.shape[-2:], mode="bilinear",
                                align_corners=False)  # fmt: skip
        return model.occupancy_head(model.fuse(torch.cat([heights, bev], dim=1)))


class DeployedDAOcc(DeployedNetwork):
    """DAOcc with a fixed projection sampling plan and BVRE grid, its LiDAR encoder run from rulebooks.

    Inputs (those of the branches the model has):

    * ``images (B, N, 3, H, W)``;
    * ``voxel_features (V, C)``: the mean point of every voxel (``LidarEncoder.voxelize``);
    * ``rules_<key> (2, K', L_key)`` int64, one per sparse convolution key of the encoder (``subm1``, ``spconv1``,
      ..., ``spconv_down2``): input rows and output rows of each kernel offset's pairs, see
      :mod:`occkit.models.sparse_rules`;
    * ``coords_<key> (N_key, 4)`` int64 ``(batch, x, y, z)``, the active sites after each strided convolution; the
      network reads their count, and places the last ones in the dense LiDAR BEV.
    """

    def __init__(self, model: DAOcc, batch: Batch) -> None:
        super().__init__()
        self.model = model
        self.input_names, self.input_docs, self.dynamic_axes = [], {}, {}
        self.batch_size = len(batch)
        if model.view_transform is not None:
            self.image_shape = tuple(batch.images.shape)
            plan = model.view_transform.plan(
                batch.intrinsics, batch.cam2ego, batch.img_aug, batch.lidar2ego, batch.bev_aug,
                image_size=tuple(batch.images.shape[-2:]), camera_mask=batch.camera_mask,
            )  # fmt: skip
            _buffers(self, sample_grid=plan.grid, sample_target=plan.target, sample_weight=plan.weight)
            self.num_voxels = plan.num_voxels
            self.input_names.append("images")
            self.input_docs["images"] = f"{self.image_shape} float32 normalised camera images (test transform)"
        grid = model.range_extension.sampling_grid(batch.lidar2ego, batch.bev_aug, batch.occ_aug)
        _buffers(self, range_grid=grid)
        self.sparse_encoder = None
        if model.lidar_encoder is not None:
            self.sparse_encoder = RulebookSparseEncoder(model.lidar_encoder.encoder, self.batch_size)
            self._describe_lidar_inputs()

    def _describe_lidar_inputs(self) -> None:
        channels = self.model.lidar_encoder.cfg.in_channels
        self.input_names.append("voxel_features")
        self.input_docs["voxel_features"] = f"(V, {channels}) float32 mean point of each voxel"
        self.dynamic_axes["voxel_features"] = {0: "voxels"}
        for spec in self.sparse_encoder.specs:
            name = f"rules_{spec.key}"
            kind = "submanifold, centre offset left out" if spec.subm else f"stride {spec.stride}"
            self.input_names.append(name)
            self.input_docs[name] = (f"(2, {len(spec.offsets)}, L) int64 rulebook of the {spec.key} convolutions "
                                     f"({kind}): input rows [0] and output rows [1] per kernel offset")
            self.dynamic_axes[name] = {2: f"pairs_{spec.key}"}
        for spec in self.sparse_encoder.strided_specs:
            name = f"coords_{spec.key}"
            self.input_names.append(name)
            self.input_docs[name] = f"(N, 4) int64 (batch, x, y, z) active sites after {spec.key}, {spec.out_shape}"
            self.dynamic_axes[name] = {0: f"sites_{spec.key}"}

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        tensors = {}
        if self.model.view_transform is not None:
            tensors["images"] = self._check_images(batch.images, self.image_shape)
        if self.sparse_encoder is not None:
            if batch.points is None or len(batch) != self.batch_size:
                raise ValueError(f"the network was made for LiDAR batches of {self.batch_size} sample(s)")
            features, coords, _ = self.model.lidar_encoder.voxelize(batch.points, batch.num_points)
            # spconv's extra z cell is never occupied, so the voxel coordinates are valid encoder sites as they are.
            pairs, out_coords = self.sparse_encoder.rulebook_tensors(coords)
            tensors["voxel_features"] = features
            tensors.update({f"rules_{s.key}": p for s, p in zip(self.sparse_encoder.specs, pairs, strict=True)})
            tensors.update({f"coords_{s.key}": c for s, c in zip(self.sparse_encoder.strided_specs, out_coords,
                                                                  strict=True)})  # fmt: skip
        return tensors

    def _camera_bev(self, features: Tensor) -> Tensor:
        """``ProjectionViewTransform.forward`` with the fixed plan, accumulating one camera at a time.

        Within one (sample, camera) every voxel is sampled once (padding aside), but a voxel seen by two cameras
        is hit twice. The one ``index_add`` of the eager module becomes a ScatterND(reduction="add") that
        onnxruntime spreads over threads without guarding repeated rows, so the export adds camera by camera.

        Args: features: ``(B, N, C_in, h, w)``. Returns: ``(B, Z * C, X, Y)``.
        """
        transform = self.model.view_transform
        batch = features.shape[0]
        flat = features.flatten(0, 1)  # (B*N, C_in, h, w)
        if transform.reduce is not None:
            flat = transform.reduce(flat)
        channels = flat.shape[1]
        sampled = F.grid_sample(flat, self.sample_grid.to(flat.dtype), mode="bilinear", padding_mode="zeros",
                                align_corners=False)  # (B*N, C, L, 1)
        sampled = sampled[..., 0].transpose(1, 2) * self.sample_weight[..., None].to(flat.dtype)  # (B*N, L, C)
        volume = flat.new_zeros(batch * self.num_voxels + 1, channels)  # the last row absorbs the padding
        for camera in range(sampled.shape[0]):
            volume.index_add_(0, self.sample_target[camera], sampled[camera])
        x, y, z = transform.cfg.grid_size
        volume = volume[:-1].view(batch, x, y, z, channels)
        return volume.permute(0, 3, 4, 1, 2).reshape(batch, z * channels, x, y)  # channel z * C + c

    def logits(self, inputs: dict[str, Tensor]) -> Tensor:
        """DAOcc's forward (``DAOcc.forward`` without detection) on the tensors named in :attr:`input_names`."""
        model = self.model
        bevs = []
        if model.view_transform is not None:
            bevs.append(self._camera_bev(model.image_encoder(inputs["images"])))  # (B, Z * C, X, Y)
        if self.sparse_encoder is not None:
            specs = self.sparse_encoder.specs
            pairs = [inputs[f"rules_{s.key}"] for s in specs]
            coords = [inputs[f"coords_{s.key}"] for s in self.sparse_encoder.strided_specs]
            bevs.append(self.sparse_encoder(inputs["voxel_features"], pairs, coords))  # (B, C', X, Y)
        bev = model.bev_encoder(model.fuser(bevs))
        extension = model.range_extension
        if extension.reduce is not None:
            bev = extension.reduce(bev)
        occ_bev = F.grid_sample(bev, self.range_grid.to(bev.dtype), mode="bilinear", padding_mode="zeros",
                                align_corners=False)  # fmt: skip
        return model.occupancy_head(occ_bev)


def deploy(model: nn.Module, batch: Batch) -> DeployedNetwork:
    """The fixed-rig inference network of ``model`` (put in eval mode) for the rig of ``batch``.

    Raises:
        ValueError: for a model that is not a FlashOcc, DA-Occ or DAOcc, or a batch without the images it needs.
    """
    model.eval()
    if getattr(model, "image_encoder", None) is not None and batch.images is None:
        raise ValueError(f"{type(model).__name__} needs camera images but the reference batch has none")
    if isinstance(model, FlashOcc):
        return DeployedFlashOcc(model, batch).eval()
    if isinstance(model, DirectionAwareOcc):
        return DeployedDirectionAwareOcc(model, batch).eval()
    if isinstance(model, DAOcc):
        return DeployedDAOcc(model, batch).eval()
    raise ValueError(f"no fixed-rig network for {type(model).__name__}; known: FlashOcc, DirectionAwareOcc, DAOcc")
