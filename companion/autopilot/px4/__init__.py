"""PX4's side of ``companion autopilot`` (``companion px4 check | configure``): make EKF2 fuse
our estimate, through MAVSDK.

- :mod:`.rules` — every row: :mod:`.ekf2_rules` (EKF2's vision fusion, timing, trust, the other
  sensors) then :mod:`.port_rules` (the companion's MAVLink instance), on :mod:`.typed_rows`
  (a row typed as PX4 declares the parameter) with :mod:`.link_context` (our side) (pure);
- :mod:`.encoding` — INT32 / REAL32 byte-wise encoding and the float-encoded-int trap (pure);
- :mod:`.ekf2_diagnosis` — is our estimate fused by EKF2, and if not the most likely reason,
  from :mod:`.ekf2_observations` and PX4's own topics (:mod:`.ekf2_shell_diagnosis`) (pure);
- :mod:`.link` — the MAVSDK session (param, telemetry, mavlink_direct, shell);
- :mod:`.check`, :mod:`.configure` — the two commands.
"""
