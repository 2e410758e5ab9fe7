"""SO(3)/SE(3) helpers and the camera model. Pure numpy."""
