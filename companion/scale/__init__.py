"""Metric scale of the monocular VO from distance sensors: MSC, MSCwK, M-MSC and baselines."""
