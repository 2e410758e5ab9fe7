"""Closed loops with the real autopilots: PX4 SIH (``companion sitl px4``) and ArduCopter SITL
(``companion sitl ardupilot``). Their physics feed the world's camera and sensors through a
bridge process (``px4_bridge``, ``ardupilot_bridge``); a flight (``px4_flight``,
``ardupilot_flight`` on the shared skeleton) starts the processes, flies a mission from a
minimal ground station and summarises (``*_results``, ``ulog``). Never imports the stub.
"""
