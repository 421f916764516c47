"""The offline map builder: SfM model -> multi-scale DAISY descriptors per 3D point, camera
clusters, ANN index, lookup tables -> one versioned map bundle (paper Sections 2 and 2.3).

One module per stage: ``sfm`` (inputs -> reconstruction), ``descriptors`` (pyramids, Harris,
DAISY, assignment to 3D points), ``clusters`` (overlapping view clustering), ``build`` (the
pipeline), ``video`` (keyframes from a video). The bundle format and the index it writes live in
``sfmloc.map``, which the online engine reads without importing this package."""
