"""Per-frame image features shared by the builder and the online engine: Harris corners,
BRIEF for tracking, oriented DAISY (+PCA) for 2D-to-3D matching, image pyramids.

Plain numpy/OpenCV; every keypoint coordinate is in COLMAP's pixel convention
(see ``sfmloc.cameras``)."""
