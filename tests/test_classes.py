"""Class taxonomies: ids, palettes and nuScenes category mappings."""

from __future__ import annotations

import pytest

from occkit.classes import (
    DETECTION_CLASSES,
    IGNORE_INDEX,
    NUSCENES_TO_DETECTION,
    NUSCENES_TO_OCC3D,
    OCC3D,
    OCC3D_CLASSES,
    OCC3D_COLORS,
    SURROUNDOCC,
    SURROUNDOCC_CLASSES,
    detection_name,
    occ3d_id,
)


def test_occ3d_ids_match_the_benchmark():
    assert len(OCC3D_CLASSES) == 18 and len(OCC3D_COLORS) == 18
    assert OCC3D_CLASSES[0] == "others" and OCC3D_CLASSES[4] == "car" and OCC3D_CLASSES[17] == "free"
    assert OCC3D_CLASSES.index("driveable_surface") == 11 and OCC3D_CLASSES.index("vegetation") == 16
    assert OCC3D.empty_index == 17 and OCC3D.semantic_ids == tuple(range(17))
    assert all(len(c) == 3 and all(0 <= v <= 255 for v in c) for c in OCC3D_COLORS)
    assert len(set(OCC3D_COLORS)) == 18


def test_surroundocc_shares_semantic_ids_with_occ3d():
    assert len(SURROUNDOCC_CLASSES) == 17 and SURROUNDOCC_CLASSES[0] == "empty"
    assert SURROUNDOCC_CLASSES[1:] == OCC3D_CLASSES[1:17]
    assert SURROUNDOCC.semantic_ids == tuple(range(1, 17)) and SURROUNDOCC.num_classes == 17


def test_detection_classes_and_mapping():
    assert len(DETECTION_CLASSES) == 10
    assert set(NUSCENES_TO_DETECTION.values()) == set(DETECTION_CLASSES)
    assert detection_name("human.pedestrian.police_officer") == "pedestrian"
    assert detection_name("vehicle.bus.bendy") == "bus"
    assert detection_name("static.manmade") is None


def test_nuscenes_categories_map_onto_occ3d():
    assert len(NUSCENES_TO_OCC3D) == 32  # the nuScenes-lidarseg category list
    assert occ3d_id("vehicle.car") == 4 and occ3d_id("flat.driveable_surface") == 11
    assert occ3d_id("movable_object.debris") == 0 and occ3d_id("noise") == IGNORE_INDEX
    # Every detection class keeps its name in Occ3D.
    for category, name in NUSCENES_TO_DETECTION.items():
        assert OCC3D_CLASSES[occ3d_id(category)] == name
    assert set(NUSCENES_TO_OCC3D.values()) == set(range(17)) | {IGNORE_INDEX}


def test_unknown_names_list_the_known_ones():
    with pytest.raises(KeyError, match="unknown nuScenes category 'vehicle.tank'.*vehicle.car"):
        occ3d_id("vehicle.tank")
    with pytest.raises(KeyError, match="unknown nuScenes category"):
        detection_name("car")
    with pytest.raises(KeyError, match="occ3d has no class 'road'; classes: others, barrier"):
        OCC3D.index("road")
    assert OCC3D.index("truck") == 10
