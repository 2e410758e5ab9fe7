"""Our output's frame against the autopilot's, while GPS comes and goes (pure): the 4-DoF
alignment of our track to the autopilot's GPS-derived one, the GPS quality verdict and the
projection of a fix into the autopilot's local NED, and the handover state machine that
aligns, holds through a GPS denial and slews back at a bounded rate (docs/gps.md)."""
