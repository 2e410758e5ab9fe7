"""ArduPilot's side of ``companion autopilot``: make EKF3 fuse our estimate, through pymavlink.

- :mod:`.rules` — the VISO_*, EK3_SRC1_*, GPS, RNGFND and link parameters, what we need of
  each and why (pure);
- :mod:`.ekf3_diagnosis` — is our estimate fused by EKF3, and if not the most likely reason
  (pure);
- :mod:`.link` — the pymavlink ground-station session;
- :mod:`.check`, :mod:`.configure` — the two commands.
"""
