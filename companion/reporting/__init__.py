"""Tables (Markdown, CSV) and PNG plots of evaluation runs. Writes files; no algorithms.

- :mod:`companion.reporting.scale`: the VO and metric-scale runs, and the summary over folders;
- :mod:`companion.reporting.pose`: the roll/pitch and d-Pose runs;
- :mod:`companion.reporting.figures`: matplotlib, loaded on first use.
"""

from __future__ import annotations

from companion.reporting.pose import attitude_metrics as attitude_metrics
from companion.reporting.pose import format_random_study as format_random_study
from companion.reporting.pose import write_attitude as write_attitude
from companion.reporting.pose import write_attitude_study as write_attitude_study
from companion.reporting.pose import write_dpose as write_dpose
from companion.reporting.pose import write_dpose_return as write_dpose_return
from companion.reporting.scale import summary as summary
from companion.reporting.scale import write_plots as write_plots
from companion.reporting.scale import write_tables as write_tables
from companion.reporting.scale import write_trajectories as write_trajectories
from companion.reporting.scale import write_vo_report as write_vo_report
