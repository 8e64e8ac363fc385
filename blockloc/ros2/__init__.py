"""ROS 2 on the wire without ROS 2: its messages as Cyclone DDS types, topics, QoS and discovery.

No dependency on the config or the application layer (the node and the player are in
:mod:`blockloc.node`)."""
