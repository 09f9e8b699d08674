"""Headless renders of occupancy, predictions and cameras: PNG files and a page that gathers them; and recordings
for rerun's interactive 3D viewer.

The renders draw with matplotlib's Agg canvas, so no display (X server) is ever needed, and nothing here changes the
global pyplot backend of an interactive session.

- :mod:`occkit.viz.palette`: the Occ3D class colours as arrays, class legends.
- :mod:`occkit.viz.bev`: bird's-eye-view semantic maps (the class of the top-most occupied voxel per column).
- :mod:`occkit.viz.voxels`: 3D voxel renders seen from behind and above the ego car.
- :mod:`occkit.viz.errors`: prediction against ground truth, voxel by voxel and as a BEV error map.
- :mod:`occkit.viz.cameras`: the six surround cameras with projected LiDAR points or occupied voxels.
- :mod:`occkit.viz.page`: a Markdown and an HTML page with the PNGs of a run.
- :mod:`occkit.viz.run`: all of the above for frames of a dataset split (what ``occkit viz`` calls).
- :mod:`occkit.viz.recording`: scenes, labels and predictions as a rerun recording on a timeline (what
  ``occkit view`` calls; needs the ``viewer`` extra, rerun-sdk).
"""
