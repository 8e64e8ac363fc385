"""The Foxglove layout and the RViz config of ``blockloc node``'s topics (shipped in ``layouts/``).

Foxglove reads the node's topics through a ROS 2 bridge (``foxglove_bridge``) or from the
``run.mcap`` of ``--out`` afterwards; RViz 2 subscribes to them directly. Both show, in the ``map``
frame following ``base_link``: the local map (/blockloc/local_map), the pose with its covariance
(/blockloc/pose), the odometry, the scan (/points), the player's ground truth, TF, and the
diagnostics. ``python -m blockloc.node.layout`` rewrites the files (a test checks they are current).
"""

from __future__ import annotations

import json
from pathlib import Path

LAYOUT_DIR = Path(__file__).with_name("layouts")
FOXGLOVE_NAME = "blockloc_node.foxglove.json"
RVIZ_NAME = "blockloc_node.rviz"
DIAG_NAME = "blockloc: localization"


def foxglove_layout_json() -> str:
    """The Foxglove layout (foxglove-sdk's typed layout model) as indented JSON."""
    import foxglove.layouts as fl

    def diag(key: str) -> str:
        return f'/diagnostics.status[0].values[:]{{key=="{key}"}}.value'

    three_d = fl.ThreeDeePanel(title="blockloc node", config=fl.ThreeDeeConfig(
        fixed_frame="map", follow_tf="base_link", follow_mode="follow-position",
        camera_state=fl.ThreeDeeCameraState(distance=80.0, perspective=True, phi=50.0, theta_offset=45.0),
        scene=fl.BaseRendererSceneSettings(background_color="#15171c",
                                           transforms=fl.BaseRendererTransforms(show_label=True, axis_size=2.0)),
        topics={
            "/blockloc/local_map": fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=1.5, color_mode="colormap", color_map="turbo", color_field="z",
                explicit_alpha=0.6),
            "/points": fl.BaseRendererPointCloudTopicSettings(visible=True, point_size=3.0, color_mode="flat",
                                                              flat_color="#ff2d55"),
            "/blockloc/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow", color="#ffd60a",
                                                               show_covariance=True, covariance_color="#ffd60a60"),
            "/blockloc/ground_truth": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow",
                                                                       color="#8e8e93"),
        }))
    plots = fl.PlotPanel(title="fitness and latency", config=fl.PlotConfig(
        paths=[fl.PlotSeries(value=diag("fitness"), label="fitness", color="#1f77b4", enabled=True),
               fl.PlotSeries(value=diag("latency_ms"), label="latency [ms]", color="#d62728", enabled=True),
               fl.PlotSeries(value=diag("dropped_scans"), label="dropped scans", color="#8c564b", enabled=True)],
        show_legend=True, legend_display="floating"))
    table = fl.DiagnosticsDetailPanel(title="diagnostics", config=fl.DiagnosticsDetailConfig(
        topic_to_render="/diagnostics", selected_hardware_id="blockloc", selected_name=DIAG_NAME,
        numeric_precision=3))
    right = fl.SplitContainer(direction="column", items=[fl.SplitItem(proportion=1, content=plots),
                                                         fl.SplitItem(proportion=1.3, content=table)])
    layout = fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(proportion=1, content=right)]))
    return json.dumps(json.loads(layout.to_json()), indent=2) + "\n"


def rviz_config_yaml() -> str:
    """An RViz 2 config (``rviz2 -d blockloc_node.rviz``)."""
    import yaml

    def display(cls: str, name: str, topic: str | None, reliability: str = "Reliable",
                durability: str = "Volatile", **extra) -> dict:
        d = {"Class": cls, "Name": name, "Enabled": True}
        if topic is not None:
            d["Topic"] = {"Value": topic, "Depth": 5, "History Policy": "Keep Last",
                          "Reliability Policy": reliability, "Durability Policy": durability}
        d.update(extra)
        return d

    displays = [
        display("rviz_default_plugins/Grid", "grid", None, **{"Reference Frame": "map", "Cell Size": 10}),
        display("rviz_default_plugins/TF", "tf", None),
        display("rviz_default_plugins/PointCloud2", "local map", "/blockloc/local_map", durability="Transient Local",
                **{"Size (m)": 0.1, "Color Transformer": "AxisColor", "Style": "Points"}),
        display("rviz_default_plugins/PointCloud2", "scan", "/points", reliability="Best Effort",
                **{"Size (m)": 0.08, "Color Transformer": "FlatColor", "Color": "255; 45; 85"}),
        display("rviz_default_plugins/PoseWithCovariance", "pose", "/blockloc/pose",
                **{"Color": "255; 214; 10", "Covariance": {"Value": True}}),
        display("rviz_default_plugins/Odometry", "odometry", "/blockloc/odom", **{"Keep": 100}),
        display("rviz_default_plugins/Odometry", "ground truth", "/blockloc/ground_truth",
                **{"Keep": 100, "Enabled": False}),
    ]
    config = {"Panels": [{"Class": "rviz_common/Displays", "Name": "Displays"}],
              "Visualization Manager": {
                  "Class": "", "Displays": displays, "Enabled": True,
                  "Global Options": {"Fixed Frame": "map", "Frame Rate": 30},
                  "Tools": [{"Class": "rviz_default_plugins/SetInitialPose",
                             "Topic": {"Value": "/initialpose"}},
                            {"Class": "rviz_default_plugins/MoveCamera"}],
                  "Views": {"Current": {"Class": "rviz_default_plugins/Orbit", "Distance": 80,
                                        "Target Frame": "base_link", "Name": "Current View"}}},
              "Window Geometry": {"Width": 1600, "Height": 1000}}
    return "# blockloc node in RViz 2: rviz2 -d blockloc_node.rviz (written by blockloc.node.layout)\n" + \
        yaml.safe_dump(config, sort_keys=False)


def write_all(directory: Path = LAYOUT_DIR) -> list[Path]:
    from blockloc.fileio import atomic_write_text

    directory.mkdir(parents=True, exist_ok=True)
    atomic_write_text(directory / FOXGLOVE_NAME, foxglove_layout_json())
    atomic_write_text(directory / RVIZ_NAME, rviz_config_yaml())
    return [directory / FOXGLOVE_NAME, directory / RVIZ_NAME]


if __name__ == "__main__":
    for path in write_all():
        print(path)
