"""The Foxglove layout shipped in docs/foxglove/: every topic and message path it names
exists in a real recording, with the fields and array elements it plots."""

from __future__ import annotations

import json
import re

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from loopcal.daemon import recording as rec
from tests.support import ROOT
from tests.support.layouts import PATH as _PATH
from tests.support.layouts import layout_paths, value_at
from tests.support.recordings import write_recording
from tests.support.rows import T0, make_rows

LAYOUT = ROOT / "docs" / "foxglove" / "loopcal-layout.json"


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
        value = value_at(first[m["topic"]], m["fields"], p)
        if m["fields"]:
            assert isinstance(value, float | int), f"{p} is not a number to plot: {value!r}"
    assert {"/joint/state", "/plate/scene", "/plate/transform", "/loopcal/log"} <= {
        _PATH.match(p)["topic"] for p in layout_paths(layout)
    }
