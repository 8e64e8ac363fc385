"""What a run looks like: the events a tracking session emits, and the observers that record,
stream or report them (MCAP for Foxglove/ROS 2, a live Foxglove server, report.html)."""
