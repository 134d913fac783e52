"""cgamap.calib: hand-eye calibration of the camera on the pan-tilt head.

handeye  motor-algebra solver (screw-line SVD) + robust refinement, OpenCV's five for comparison
axes     pan/tilt axis lines, their common perpendicular (T_axis), non-orthogonality
targets  chessboard / ChArUco drawing, detection and solvePnP
sim      simulated rig (hidden mount, rendered target) for ``calib collect --sim``
collect  the collection loop (pan-tilt driver or its twin, camera, quality checks)
pairs    pose-pair files in, calibration YAML out
cli      ``cgamap calib hand-eye`` / ``cgamap calib collect``
"""
