"""d-Pose: a direct metric 6DoF pose from four laser marks left on the surface."""
