"""Occupancy labels built from a dataset's sensor data (``occkit label``): LiDAR sweeps with lidarseg, boxes,
poses and calibration in; Occ3D or SurroundOcc label files out.

* :mod:`.sources`: the scenes' sweeps, boxes (interpolated between key frames) and cameras, from the tables;
* :mod:`.aggregate`: static points in the world and object points in their boxes, over all sweeps;
* :mod:`.voxels`: one key frame's points, majority vote, Poisson densification;
* :mod:`.pipeline`: per scene and per key frame, masks and files, scenes in parallel.

docs/labels.md describes the pipeline and measures it against the synthetic world's exact labels.
"""
