"""The live edge: the ROS 2 localization node and the sequence player (over :mod:`blockloc.ros2`)."""
