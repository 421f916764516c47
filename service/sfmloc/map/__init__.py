"""The map bundle: the format the builder writes and the engine and server read.

``bundle`` (format, atomic writing, loading, verification), ``index`` (the ANN index over the
PCA-reduced descriptors), ``keypoint_scales`` (the scales at which the mapping images saw each
point, for the online working scale) and ``report`` (points per image, track lengths, coverage).
This package imports neither the builder nor the engine: both depend on it, not on each other."""
