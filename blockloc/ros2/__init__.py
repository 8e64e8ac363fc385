"""ROS 2 on the wire without ROS 2: its messages as Cyclone DDS types, topics, QoS and discovery.

A low layer beside the ground floor: it imports only :mod:`blockloc.geometry`,
:mod:`blockloc.errors` and cyclonedds, never the config, the application layer or the core
(frames, sessions: the node and the player in :mod:`blockloc.node` turn messages into them)."""
