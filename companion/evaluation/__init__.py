"""Metrics (ATE, RPE, scale errors, angle RMSE) and report tables. Pure: no I/O."""
