"""The synthetic driving world: procedural scenes, six cameras and a LiDAR, occupancy labels, nuScenes layout."""
