"""``companion autopilot check | configure``: make the autopilot, PX4 or ArduPilot (told apart
by its HEARTBEAT), actually fuse our estimate. ``companion px4 check | configure`` is the PX4
side's own spelling.

Shared by both autopilots:

- :mod:`.params` — the parameter model: a parameter, a table row, its status, the value to
  write, a rule's judgement (pure);
- :mod:`.verdict` — the verdict of a fusion diagnosis (pure);
- :mod:`.options` — the commands' options (the flags are built from them);
- :mod:`.reach` — which link reaches the autopilot, spelled for MAVSDK or pymavlink;
- :mod:`.report` — what check prints, and the running service's status;
- :mod:`.configure` — the configure flow: plan -> confirm -> write -> read back, over a small
  link protocol (:class:`.configure.ParamLink`);
- :mod:`.cli` — the argparse wiring and the dispatch by autopilot.

Beside each other, one package per autopilot with the same rooms: ``rules`` (what we need of
each parameter and why, pure), a fusion diagnosis (pure), ``link`` (the session), ``check``
and ``configure`` (the two commands):

- :mod:`.px4` — EKF2, through MAVSDK and PX4's MAVLink shell;
- :mod:`.ardupilot` — EKF3, through pymavlink.
"""
