"""Keyframe-based sparse monocular visual odometry (pure: numpy + OpenCV, no I/O).

Entry point: :class:`companion.vo.odometry.VisualOdometry` (the facade and the tracking
step). Beside it, as SVO splits a VO: ``frontend`` (corners, KLT tracks), ``map`` (keyframes,
points, triangulation, local BA), ``keyframes`` (when to take one, its gravity prior),
``states`` (INITIALIZING / TRACKING / LOST and how a map starts); the geometry in
``initializer``, ``pose``, ``triangulation``, ``ba``; ``frame_check`` screens camera frames.
"""
