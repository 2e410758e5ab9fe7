"""The PX4-like SITL autopilot (``companion sitl run``), run in our own process against the
simulated world: the autopilot and its links (``autopilot``, ``options``), its camera process
(``camera``), its report (``report``), what it emulates of PX4 (``px4_services``,
``px4_params``, ``ekf_fusion``, ``px4_shell``), the faults it injects (``faults``), and two
tools that fly against it: the soak benchmark (``soak``) and a MAVLink flood (``flood``).
"""
