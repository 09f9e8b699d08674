"""Class taxonomies of the occupancy benchmarks and of nuScenes detection.

Ids follow each benchmark's files exactly: Occ3D-nuScenes uses 0..16 for semantic classes and 17 for free space;
SurroundOcc uses 0 for empty and 1..16 for the same semantic classes; OpenOcc v2 (the CVPR 2024 occupancy-and-flow
challenge) has no ``others``, orders the 16 classes objects first and uses 16 for free space; 255 is ignored
everywhere.
Plain Python only (no numpy/torch), so the CLI can list classes without heavy imports.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "IGNORE_INDEX",
    "Taxonomy",
    "OCC3D_CLASSES",
    "OCC3D_COLORS",
    "UNOBSERVED_COLOR",
    "EMPTY_COLOR",
    "IGNORE_COLOR",
    "OCC3D",
    "SURROUNDOCC_CLASSES",
    "SURROUNDOCC",
    "OPENOCC_CLASSES",
    "OPENOCC",
    "OCC3D_TO_OPENOCC",
    "THING_CLASSES",
    "DETECTION_CLASSES",
    "NUSCENES_TO_OCC3D",
    "NUSCENES_TO_DETECTION",
    "LIDARSEG_CATEGORIES",
    "LIDARSEG_TO_OCC3D",
    "occ3d_id",
    "lidarseg_index",
    "detection_name",
    "TAXONOMIES",
]

#: Label value that losses and metrics skip.
IGNORE_INDEX = 255

#: Occ3D-nuScenes class names in id order (17 = free).
OCC3D_CLASSES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)

#: RGB palette used by the field's Occ3D visualisers (one colour per id in OCC3D_CLASSES).
OCC3D_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # others
    (255, 120, 50),  # barrier: orange
    (255, 192, 203),  # bicycle: pink
    (255, 255, 0),  # bus: yellow
    (0, 150, 245),  # car: blue
    (0, 255, 255),  # construction_vehicle: cyan
    (200, 180, 0),  # motorcycle: dark yellow
    (255, 0, 0),  # pedestrian: red
    (255, 240, 150),  # traffic_cone: light yellow
    (135, 60, 0),  # trailer: brown
    (160, 32, 240),  # truck: purple
    (255, 0, 255),  # driveable_surface: magenta
    (139, 137, 137),  # other_flat: grey
    (75, 0, 75),  # sidewalk: dark purple
    (150, 240, 80),  # terrain: light green
    (230, 230, 250),  # manmade: lavender white
    (0, 175, 0),  # vegetation: green
    (255, 255, 255),  # free: white
)
#: Columns that no camera observes (outside the camera mask): dark, so observed content stands out.
UNOBSERVED_COLOR = (30, 30, 30)
#: Observed columns that hold no occupied voxel: a grey lighter than unobserved columns and darker than any class
#: but ``others`` (the palette's white is free space, too close to ``manmade`` to read as "nothing here").
EMPTY_COLOR = (75, 75, 75)
#: Voxels labelled 255 (ignored by losses and metrics).
IGNORE_COLOR = (128, 128, 128)

#: SurroundOcc class names in id order (0 = empty; 1..16 are Occ3D's 1..16).
SURROUNDOCC_CLASSES: tuple[str, ...] = ("empty",) + OCC3D_CLASSES[1:17]

#: OpenOcc v2 class names in id order (16 = free), as the challenge's ``ray_metrics.py`` lists them.
OPENOCC_CLASSES: tuple[str, ...] = ("car", "truck", "trailer", "bus", "construction_vehicle", "bicycle", "motorcycle",
                                    "pedestrian", "traffic_cone", "barrier", "driveable_surface", "other_flat",
                                    "sidewalk", "terrain", "manmade", "vegetation", "free")  # fmt: skip

#: OpenOcc v2 id of each Occ3D id (``OCC3D_TO_OPENOCC[occ3d_id]``), by class name; Occ3D's ``others`` has no
#: OpenOcc v2 class and becomes free space, as in the public Occ3D-to-OpenOcc conversions.
OCC3D_TO_OPENOCC: tuple[int, ...] = tuple(
    OPENOCC_CLASSES.index(name) if name in OPENOCC_CLASSES else OPENOCC_CLASSES.index("free") for name in OCC3D_CLASSES
)

#: Occ3D classes whose objects are instances of their own in panoptic occupancy (SparseOcc's RayPQ and
#: Panoptic-FlashOcc); every other class is stuff.
THING_CLASSES: tuple[str, ...] = ("car", "truck", "construction_vehicle", "bus", "trailer", "motorcycle", "bicycle",
                                  "pedestrian")  # fmt: skip

#: nuScenes detection classes in the order of mmdetection3d / BEVFusion / DAOcc configs.
DETECTION_CLASSES: tuple[str, ...] = (
    "car",
    "truck",
    "construction_vehicle",
    "bus",
    "trailer",
    "barrier",
    "motorcycle",
    "bicycle",
    "pedestrian",
    "traffic_cone",
)


@dataclass(frozen=True)
class Taxonomy:
    """Names and special ids of one label set.

    Attributes:
        name: short identifier (``"occ3d"``, ``"surroundocc"``).
        classes: class names in id order.
        empty_index: id of free / empty space.
        colors: RGB per id, or empty when the benchmark has no customary palette.
    """

    name: str
    classes: tuple[str, ...]
    empty_index: int
    colors: tuple[tuple[int, int, int], ...] = ()
    ignore_index: int = IGNORE_INDEX

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def semantic_ids(self) -> tuple[int, ...]:
        """Ids averaged by mIoU: every class but empty/free."""
        return tuple(i for i in range(self.num_classes) if i != self.empty_index)

    def index(self, class_name: str) -> int:
        try:
            return self.classes.index(class_name)
        except ValueError:
            raise KeyError(f"{self.name} has no class {class_name!r}; classes: {', '.join(self.classes)}") from None


OCC3D = Taxonomy("occ3d", OCC3D_CLASSES, empty_index=17, colors=OCC3D_COLORS)
SURROUNDOCC = Taxonomy(
    "surroundocc", SURROUNDOCC_CLASSES, empty_index=0, colors=((255, 255, 255),) + OCC3D_COLORS[1:17]
)
OPENOCC = Taxonomy("openocc", OPENOCC_CLASSES, empty_index=16,
                   colors=tuple(OCC3D_COLORS[OCC3D_CLASSES.index(name)] for name in OPENOCC_CLASSES))  # fmt: skip
TAXONOMIES: dict[str, Taxonomy] = {t.name: t for t in (OCC3D, SURROUNDOCC, OPENOCC)}

# nuScenes category -> Occ3D id, following the nuScenes-lidarseg 16-class merge. Categories that merge drops
# (animals, debris, strollers, emergency vehicles, ...) become Occ3D's "others"; noise and the ego vehicle are ignored.
NUSCENES_TO_OCC3D: dict[str, int] = {
    "noise": IGNORE_INDEX,
    "animal": 0,
    "human.pedestrian.adult": 7,
    "human.pedestrian.child": 7,
    "human.pedestrian.construction_worker": 7,
    "human.pedestrian.personal_mobility": 0,
    "human.pedestrian.police_officer": 7,
    "human.pedestrian.stroller": 0,
    "human.pedestrian.wheelchair": 0,
    "movable_object.barrier": 1,
    "movable_object.debris": 0,
    "movable_object.pushable_pullable": 0,
    "movable_object.trafficcone": 8,
    "static_object.bicycle_rack": 0,
    "vehicle.bicycle": 2,
    "vehicle.bus.bendy": 3,
    "vehicle.bus.rigid": 3,
    "vehicle.car": 4,
    "vehicle.construction": 5,
    "vehicle.emergency.ambulance": 0,
    "vehicle.emergency.police": 0,
    "vehicle.motorcycle": 6,
    "vehicle.trailer": 9,
    "vehicle.truck": 10,
    "flat.driveable_surface": 11,
    "flat.other": 12,
    "flat.sidewalk": 13,
    "flat.terrain": 14,
    "static.manmade": 15,
    "static.other": 0,
    "static.vegetation": 16,
    "vehicle.ego": IGNORE_INDEX,
}

#: nuScenes-lidarseg categories in the order of their ``index`` (0 = noise .. 31 = vehicle.ego), the per-point
#: values of ``lidarseg/<version>/<token>_lidarseg.bin``.
LIDARSEG_CATEGORIES: tuple[str, ...] = tuple(NUSCENES_TO_OCC3D)
#: Occ3D id of each lidarseg index (``LIDARSEG_TO_OCC3D[i]`` for the category of index ``i``).
LIDARSEG_TO_OCC3D: tuple[int, ...] = tuple(NUSCENES_TO_OCC3D.values())

# nuScenes category -> detection class (the devkit's category_to_detection_name); others are not detection targets.
NUSCENES_TO_DETECTION: dict[str, str] = {
    "movable_object.barrier": "barrier",
    "vehicle.bicycle": "bicycle",
    "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus",
    "vehicle.car": "car",
    "vehicle.construction": "construction_vehicle",
    "vehicle.motorcycle": "motorcycle",
    "human.pedestrian.adult": "pedestrian",
    "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "human.pedestrian.police_officer": "pedestrian",
    "movable_object.trafficcone": "traffic_cone",
    "vehicle.trailer": "trailer",
    "vehicle.truck": "truck",
}


def occ3d_id(category: str) -> int:
    """Occ3D id of a nuScenes category name (``"vehicle.car"`` -> 4); KeyError lists the known names."""
    try:
        return NUSCENES_TO_OCC3D[category]
    except KeyError:
        raise KeyError(f"unknown nuScenes category {category!r}; known: {', '.join(NUSCENES_TO_OCC3D)}") from None


def lidarseg_index(category: str) -> int:
    """nuScenes-lidarseg index of a category name (``"vehicle.car"`` -> 17); KeyError lists the known names."""
    occ3d_id(category)  # the same check and message
    return LIDARSEG_CATEGORIES.index(category)


def detection_name(category: str) -> str | None:
    """Detection class of a nuScenes category, or None for categories that are not detection targets."""
    if category not in NUSCENES_TO_OCC3D:
        raise KeyError(f"unknown nuScenes category {category!r}; known: {', '.join(NUSCENES_TO_OCC3D)}")
    return NUSCENES_TO_DETECTION.get(category)
