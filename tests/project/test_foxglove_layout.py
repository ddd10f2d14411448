"""The Foxglove layout shipped in docs/foxglove/: every topic and message path it names
exists in a real recording, with the fields and array elements it plots."""

from __future__ import annotations

import json
import re

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from loopcal.daemon import recording as rec
from tests.support import ROOT
from tests.support.recordings import write_recording
from tests.support.rows import T0, make_rows

LAYOUT = ROOT / "docs" / "foxglove" / "loopcal-layout.json"
_PATH = re.compile(r"^(?P<topic>/[\w/]+)(?P<fields>(?:\.\w+(?:\[\d+\])?)*)$")


def layout_paths(layout: dict) -> list[str]:
    """Every topic or message path the panels of a layout use."""
    paths = []
    for panel_id, cfg in layout["configById"].items():
        kind = panel_id.split("!")[0]
        if kind == "Plot":
            paths += [p["value"] for p in cfg["paths"]]
        elif kind == "3D":
            paths += list(cfg.get("topics", {}))
        elif kind == "RosOut":
            paths.append(cfg["topicToRender"])
        elif kind == "RawMessages":
            paths.append(cfg["topicPath"])
        else:
            raise AssertionError(f"a panel this test does not know: {panel_id}")
    return paths


def test_every_path_in_the_layout_exists_in_a_recording(tmp_path):
    layout = json.loads(LAYOUT.read_text())
    panels = set(layout["configById"])
    placed = set(re.findall(r'"([\w ]+![\w]+)"', json.dumps(layout["layout"])))
    assert placed == panels  # every panel is placed, every placed one configured
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, make_rows(200))  # raw scans, views, the scene, events
    first: dict[str, object] = {}
    ros2 = DecoderFactory()
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic in first:
                continue
            if channel.message_encoding == "json":
                first[channel.topic] = json.loads(message.data)
            else:  # as Foxglove decodes it: the ROS 2 message definition, CDR
                first[channel.topic] = ros2.decoder_for("cdr", schema)(message.data)
    for p in layout_paths(layout):
        m = _PATH.match(p)
        assert m, f"not a message path: {p}"
        assert m["topic"] in first, f"{p}: no topic {m['topic']} in a recording"
        value = first[m["topic"]]
        for name, index in re.findall(r"\.(\w+)(?:\[(\d+)\])?", m["fields"]):
            value = value[name] if isinstance(value, dict) else getattr(value, name)
            if index:
                assert int(index) < len(value), f"{p}: {name} has {len(value)} elements"
                value = value[int(index)]
        if m["fields"]:
            assert isinstance(value, float | int), f"{p} is not a number to plot: {value!r}"
    assert {"/joint/state", "/plate/scene", "/plate/transform", "/loopcal/log"} <= {
        _PATH.match(p)["topic"] for p in layout_paths(layout)
    }
