"""The file and figure side of ``companion calibrate``.

- :mod:`companion.calibration.files`: image folders and the laser check's ``ranges.csv``.
- :mod:`companion.calibration.figures`: the intrinsics summary, the corner coverage image and
  the laser-check overlays that ``companion calibrate`` shows.

The maths (boards, intrinsics, the laser check) is :mod:`companion.calibration_maths`, in the
algorithms' layer; the ``companion calibrate ...`` subcommands are :mod:`companion.cli.calibrate`
(reads through ``files``, writes the reports).
"""
