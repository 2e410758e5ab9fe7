"""The simulated world: terrain (``terrain``: NED, heights positive up; numba ``_kernels``), the
flight (``trajectory``), the camera (``render``), distance sensors and attitude (``sensors``),
the whole frame-by-frame stream (``scenario``), recorded datasets (``dataset``) and synthetic
``companion calibrate`` inputs (``calibration``). Imports neither the stub nor the loops.
"""
