"""See a run: MCAP recordings of ROS 2 messages, a live Foxglove WebSocket view, a Foxglove layout
and a self-contained HTML report.

- :mod:`blockloc.viz.events`: ``RunInfo``, ``FrameEvent``, the ``RunObserver`` protocol.
- :mod:`blockloc.viz.ros_messages`: topics, frames, decimation (shared by the two observers).
- :mod:`blockloc.viz.mcap_recorder`: ``McapRecorder`` (a RunObserver writing ``run.mcap``).
- :mod:`blockloc.viz.live`: ``LiveServer`` (a RunObserver serving Foxglove over WebSocket).
- :mod:`blockloc.viz.layout`: the Foxglove layout and ``view_instructions(run_dir)``.
- :mod:`blockloc.viz.report`: ``write_report(...)`` -> ``report.html``.

Importing this package imports none of mcap, rosbags, foxglove or matplotlib; each module that
needs one imports it when used.
"""

from blockloc.viz.events import FrameEvent, ObserverGroup, RunInfo, RunObserver, VizError

__all__ = ["FrameEvent", "ObserverGroup", "RunInfo", "RunObserver", "VizError"]
