"""Software-in-the-loop stub: a simulated world, its sensors, and (later) a PX4-like autopilot."""
