"""The Foxglove layouts shipped in docs/foxglove/: the message paths their panels name, and
the value a path picks out of a decoded message."""

from __future__ import annotations

import re
from typing import Any

#: a topic and a message path, /topic.field[index].field ...
PATH = re.compile(r"^(?P<topic>/[\w/]+)(?P<fields>(?:\.\w+(?:\[\d+\])?)*)$")


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


def value_at(message: Any, fields: str, path: str) -> Any:
    """The value ``.a.b[2]`` (``fields``) of a decoded message (dicts or objects); fails
    naming ``path`` where an index is out of range."""
    value = message
    for name, index in re.findall(r"\.(\w+)(?:\[(\d+)\])?", fields):
        value = value[name] if isinstance(value, dict) else getattr(value, name)
        if index:
            assert int(index) < len(value), f"{path}: {name} has {len(value)} elements"
            value = value[int(index)]
    return value
