"""README's "On a robot": its lines run as typed (loopback DDS set), and the layouts it names are
in the repo and current."""

from __future__ import annotations

import json
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from tests.faults.conftest import blockloc_env
from tests.node.conftest import wait_until
from tests.node.test_cli_node import listen

REPO = Path(__file__).resolve().parents[2]


def robot_lines() -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text.split("## On a robot", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    return [ln.split(" #")[0].strip() for ln in block.splitlines() if ln.strip()]


def test_the_readme_lines_run_as_typed(tiny_live_world, loopback_dds, tmp_path):
    lines = robot_lines()
    assert [ln.split()[:2] for ln in lines] == [["blockloc", "play"], ["blockloc", "node"], ["rviz2", "-d"]]
    # "Everyday use" made sim_out/loc and maps/small; here they are the tiny world's
    (tmp_path / "sim_out").mkdir()
    (tmp_path / "maps").mkdir()
    (tmp_path / "sim_out" / "loc").symlink_to(tiny_live_world["session"])
    (tmp_path / "maps" / "small").symlink_to(tiny_live_world["map"])
    play_words = shlex.split(lines[0].rstrip("&"))
    node_words = shlex.split(lines[1])
    assert lines[0].endswith("&")  # in the background, beside the node
    env = blockloc_env()

    def start(words):
        return subprocess.Popen([sys.executable, "-m", "blockloc.cli", *words[1:]], cwd=tmp_path, env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    dds, got = listen()
    node = start(node_words)
    play = None
    try:
        time.sleep(3.0)
        play = start(play_words)
        wait_until(lambda: len(got["pose"]) >= 20, 120, "poses from the node")
        node.send_signal(signal.SIGINT)
        _, err = node.communicate(timeout=120)
        assert node.returncode == 130, err
    finally:
        for p in (node, play):
            if p is not None and p.poll() is None:
                p.kill()
                p.communicate(timeout=10)
        dds.close()
    assert (tmp_path / "runs" / "live" / "report.html").is_file()
    assert (tmp_path / "runs" / "live" / "run.mcap").is_file()
    # the third line names the RViz config shipped in the repo
    assert (REPO / shlex.split(lines[2])[2]).is_file()


def test_the_shipped_layouts_are_current_and_name_the_node_topics():
    from blockloc.node import layout

    fox = layout.LAYOUT_DIR / layout.FOXGLOVE_NAME
    rviz = layout.LAYOUT_DIR / layout.RVIZ_NAME
    assert fox.read_text() == layout.foxglove_layout_json(), "python -m blockloc.node.layout rewrites it"
    assert rviz.read_text() == layout.rviz_config_yaml(), "python -m blockloc.node.layout rewrites it"
    topics = json.loads(fox.read_text())
    text = json.dumps(topics)
    for topic in ("/blockloc/local_map", "/blockloc/pose", "/points", "/diagnostics"):
        assert topic in text
    cfg = yaml.safe_load(rviz.read_text())
    vm = cfg["Visualization Manager"]
    assert vm["Global Options"]["Fixed Frame"] == "map"
    by_topic = {d["Topic"]["Value"]: d for d in vm["Displays"] if "Topic" in d}
    assert {"/blockloc/local_map", "/blockloc/pose", "/blockloc/odom", "/points"} <= set(by_topic)
    # QoS as the node publishes: the local map latched, the scan best effort
    assert by_topic["/blockloc/local_map"]["Topic"]["Durability Policy"] == "Transient Local"
    assert by_topic["/points"]["Topic"]["Reliability Policy"] == "Best Effort"
    assert any(t["Class"].endswith("SetInitialPose") and t["Topic"]["Value"] == "/initialpose" for t in vm["Tools"])
