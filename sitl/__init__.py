"""The simulator, in three wings (``companion sitl ...``, reached only from companion.cli.sim).

- :mod:`companion.sitl.world`: the simulated world and what it produces. Seeded terrains with
  exact ray casting (numba kernels), smooth trajectories, the rendered camera, the distance
  sensors and attitude, a whole flight's stream (scenario), recorded datasets and synthetic
  calibration inputs. It knows nothing of autopilots.
- :mod:`companion.sitl.stub`: a PX4-like SITL autopilot in our own process (``companion sitl
  run``) and what it emulates of PX4 (parameters, EKF2's EV fusion, the nsh shell, a ground
  station endpoint), the faults it injects, the soak benchmark and a MAVLink flood. It flies
  the world's trajectory and streams the world's camera and sensors.
- :mod:`companion.sitl.loops`: closed loops with the real autopilots (PX4 SIH, ArduCopter
  SITL): bridges from their physics to the world's camera and sensors, the flights (processes,
  ground station, mission) and their results. They never use the stub.

The wings' imports point one way (contracts in pyproject.toml): stub -> world, loops -> world.
"""
