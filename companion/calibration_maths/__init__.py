"""The maths of camera and sensor calibration: pure functions and frozen results (numpy,
OpenCV, arrays in, results out; no files, no command line), in the algorithms' layer.

- :mod:`companion.calibration_maths.board`: calibration boards (chessboard, ChArUco): the spec
  given on the command line, the printable image, sub-pixel corner detection.
- :mod:`companion.calibration_maths.intrinsics`: camera intrinsics and distortion (k1 k2 p1 p2
  k3, the model of :class:`companion.geometry.camera.CameraModel`) from board views, with the
  reprojection errors and parameter standard deviations a user needs to judge them.
- :mod:`companion.calibration_maths.lasers`: checks the distance sensors' extrinsics against
  images with the lasers on: each red dot should land where the model projects the laser's
  hit point (the dots found by the d-Pose detector, :mod:`companion.dpose.detect`).

What reads the images and writes the reports is :mod:`companion.calibration` (files, figures)
and :mod:`companion.cli.calibrate` (the ``companion calibrate`` subcommands).
"""
