"""Calibration helpers behind ``companion calibrate`` (issue 8).

- :mod:`companion.calibration.board`: calibration boards (chessboard, ChArUco): the spec given on
  the command line, the printable image, sub-pixel corner detection.
- :mod:`companion.calibration.intrinsics`: camera intrinsics and distortion (k1 k2 p1 p2 k3,
  the model of :class:`companion.geometry.camera.CameraModel`) from board views, with the
  reprojection errors and parameter standard deviations a user needs to judge them.
- :mod:`companion.calibration.lasers`: checks the distance sensors' extrinsics against images
  with the lasers on: each red dot should land where the model projects the laser's hit point.
- :mod:`companion.calibration.files`: image folders and the laser check's ``ranges.csv``.
- :mod:`companion.calibration.figures`: the intrinsics summary, the corner coverage image and
  the laser-check overlays that ``companion calibrate`` shows.

The ``companion calibrate ...`` subcommands are :mod:`companion.cli.calibrate` (reads through
``files``, writes the reports).

The first three are pure (numpy / OpenCV, arrays in, frozen results out), like the other
algorithm packages (DESIGN.md section 1).
"""
