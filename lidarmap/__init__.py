"""lidarmap: LiDAR point clouds of cities to building models that improve with every new scan."""

__version__ = "0.1.0"
