"""Roll and pitch from three or more distance sensors, bias-compensated with the VO cloud."""
