"""``companion px4 check | configure``: make PX4 actually fuse our estimate (through MAVSDK).

- :mod:`companion.px4.rules` — the parameters that govern external vision and the companion
  link, what we need of each and why (pure);
- :mod:`companion.px4.encoding` — INT32 / REAL32 byte-wise encoding and the float-encoded-int
  trap (pure);
- :mod:`companion.px4.shell` — PX4's MAVLink shell (nsh) output parsers and session;
- :mod:`companion.px4.fusion` — is our estimate fused, and if not the most likely reason (pure);
- :mod:`companion.px4.link` — the MAVSDK session (param, telemetry, mavlink_direct, shell);
- :mod:`companion.px4.check`, :mod:`companion.px4.configure` — the two commands;
- :mod:`companion.px4.cli` — their argparse wiring.
"""
