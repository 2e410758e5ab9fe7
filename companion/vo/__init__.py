"""Keyframe-based sparse monocular visual odometry (pure: numpy + OpenCV, no I/O).

Entry point: :class:`companion.vo.odometry.VisualOdometry`.
"""
