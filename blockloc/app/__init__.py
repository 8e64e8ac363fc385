"""The application layer: the only layer below the commands that reads the config.

- ``catalog``: ``--seq`` names and paths -> a Sequence, the preset that fits, the default map.
- ``assemble``: config sections -> engine, map store and provider, localizer, tracker, session.
- ``session``: the Session (init modes, step, relocalize, finish), with ``recovery`` (global init
  and relocalization) and ``stream_checks`` (IMU and LiDAR gaps).
- ``runs``: the recipes the commands, the benchmarks and a live node share (open a session,
  global init of one frame, build a map and its place index, the demo's world).
- ``lifelong``: change detection and map updates from runs (the run's sequence and config; the
  core is ``blockloc.maps.changes``).
"""
