"""Self-calibration of a camera rig (pure numpy/scipy/OpenCV): the shared bundle adjustment
(:mod:`.bundle`) and the people mode (correspondences from skeletons, initial rig, world frame,
time offsets, report)."""
