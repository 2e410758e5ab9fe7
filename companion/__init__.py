"""companion: metric visual odometry and drift-free attitude for PX4 from a camera and lasers."""

__version__ = "0.1.0"
