"""blockloc: LiDAR-inertial localization in large prior maps, one block at a time."""

__version__ = "0.1.0"
