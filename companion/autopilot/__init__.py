"""``companion autopilot check | configure``: PX4 or ArduPilot, told apart by its HEARTBEAT.

PX4 goes to :mod:`companion.px4` (``companion px4 check | configure`` is its own spelling);
ArduPilot is here:

- :mod:`companion.autopilot.ardupilot_rules` — the VISO_*, EK3_SRC1_*, GPS, RNGFND and link
  parameters, what we need of each and why (pure);
- :mod:`companion.autopilot.ardupilot_fusion` — is our estimate fused by EKF3, and if not the
  most likely reason (pure);
- :mod:`companion.autopilot.ardupilot_link` — the pymavlink ground-station session;
- :mod:`companion.autopilot.ardupilot_check` — the two commands on ArduPilot;
- :mod:`companion.autopilot.cli` — the argparse wiring and the dispatch by autopilot.
"""
