"""Camera calibration from ChArUco shots: the board definition (``board``), detection and per-camera intrinsics
(``charuco``), rig initialisation and the joint bundle adjustment (``rig``, on the sparse Levenberg-Marquardt
solver in ``sparse_lm``), and the comparison and figures of the report (``report``).
"""
