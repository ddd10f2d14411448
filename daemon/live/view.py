"""The live view: a running recorder's channels served to Foxglove (or Lichtblick) over the
Foxglove WebSocket protocol (``foxglove.websocket.v1``, which the vendor's ``foxglove-sdk``,
used here, serves under its new name ``foxglove.sdk.v1``: docs/tools.md).

What a viewer gets, with the recording's own topics and schemas (docs/recording.md), so the
layout that opens a recording opens the live session too:

- ``/joint/state``, ``/plate/transform``: every scan's view, at the scan rate;
- ``/plate/scene``: the mechanism, again every :data:`SCENE_EVERY_S` (a viewer that joins
  late sees it);
- ``/loopcal/events``, ``/loopcal/log``: every event as it is emitted;
- ``/loopcal/health``: the loop-closure test after each still pose (statistic, shift and
  its standard deviation per sensor, the threshold, the alarm);
- ``/loopcal/guidance`` (``record --until-enough``): what has been collected, the predicted
  standard deviation of each parameter, the instruction, ``enough``; and
  ``/loopcal/guidance/tilt``: the next direction to tilt, an arrow in the 3D scene.

Read-only: the server advertises no capability (no parameters, services, publishing or
client channels). The per-scan views are not computed again: the recording's writer hands
the ones it has just put in the file over a bounded queue (:data:`QUEUE` messages) to a
thread of the live view's own, which gives them to the server (the SDK's threads) if
someone subscribes; the writer only appends to that queue and returns. So the live view
shows a scan once it is in the file (at most a flush period, ``[recording].flush_period``,
later), and shows at the controller config the file records. A client that cannot keep up
has its oldest messages dropped by the server (:data:`BACKLOG` per client, not counted:
the SDK does not say); a live view that cannot keep up drops the oldest of its queue, and
counts them (:attr:`LiveView.dropped`, the metric ``loopcal_live_dropped_messages``):
never a scan of the recording. The health and the scene come from the analysis thread
(the live view is an observer, after the health monitor); events from whichever thread
emits them.

Imports: foxglove-sdk, the recording format's views and schemas, the recorder's settings
(the address) and metrics (what a bound address exposes).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
from prometheus_client.core import CounterMetricFamily

from loopcal.calibration.kinematics import base_points

from ..config.controller import ControllerConfig
from ..events import Event
from ..recorder.metrics import exposed
from ..recorder.settings import SettingsError, parse_listen
from ..recording.schemas import (
    BASE_FRAME,
    CHANNELS,
    NS_PER_S,
    TOPIC_EVENTS,
    TOPIC_LOG,
    TOPIC_SCENE,
    TOPIC_STATE,
    TOPIC_TRANSFORM,
    schema_bytes,
)
from ..recording.views import WrittenViews, scene_message
from ..recording.writer import log_entry
from .guidance import GuidanceUpdate
from .health import HealthMonitor

log = logging.getLogger(__name__)

#: messages the server keeps per client before it drops the oldest (about 25 s of views at
#: 20 Hz: two a scan)
BACKLOG = 1024
#: messages of scan views waiting between the recording's writer and the live view's
#: thread: no more than the server keeps for a client (more would be dropped there)
QUEUE = BACKLOG
#: seconds between two /plate/scene messages (a viewer that joins sees it within this)
SCENE_EVERY_S = 2.0
TOPIC_HEALTH = "/loopcal/health"
TOPIC_GUIDANCE = "/loopcal/guidance"
TOPIC_TILT = "/loopcal/guidance/tilt"

_NUMBERS = {"type": "array", "items": {"type": "number"}}
_JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    TOPIC_HEALTH: {
        "type": "object",
        "title": "loopcal.Health",
        "properties": {
            "timestamp": {"type": "object", "properties": {
                "sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "poses": {"type": "integer"},
            "statistic": _NUMBERS,
            "shift_mm": _NUMBERS,
            "std_mm": _NUMBERS,
            "threshold": {"type": "number"},
            "alarm_sensor": {"type": "integer"},
            "loops_open": {"type": "boolean"},
            "status": {"type": "string"},
        },
    },
    TOPIC_GUIDANCE: {
        "type": "object",
        "title": "loopcal.Guidance",
        "properties": {
            "elapsed_s": {"type": "number"},
            "scans": {"type": "integer"},
            "poses": {"type": "integer"},
            "reach_deg": _NUMBERS,
            "twist_deg": _NUMBERS,
            "std": {"type": "object", "additionalProperties": {"type": "number"}},
            "target_mm": {"type": "number"},
            "enough": {"type": "boolean"},
            "instruction": {"type": "string"},
        },
    },
}  # fmt: skip


def _stamp(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), NS_PER_S)
    return {"sec": sec, "nsec": nsec}


class LiveView:
    """An observer serving the recorder's channels on ``listen`` ("HOST:PORT", a port of
    1..65535), and a listener of the recording's views (:meth:`views`). Raises
    SettingsError naming ``[live].listen`` if it cannot listen there. Call :meth:`close`
    when the recorder stops."""

    name = "live view"

    def __init__(self, listen: str, controller: ControllerConfig, *,
                 health: HealthMonitor | None = None) -> None:  # fmt: skip
        import foxglove  # here: a recorder without a live view never loads the SDK

        self._fx = foxglove
        host, port = parse_listen(listen)
        self.params = np.array(controller.params, dtype=float)
        self.health = health
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name="loopcal", host=host, port=port, context=self.context, capabilities=[],
                message_backlog_size=BACKLOG,
            )  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - the SDK's bind errors have no common type
            raise SettingsError(f"cannot serve the live view on {listen}: {exc}",
                                "live_listen") from None  # fmt: skip
        self.port = self.server.port
        self.url = f"ws://{host}:{self.port}"
        self._lock = threading.Lock()  # events come from any thread
        self._channels: dict[str, Any] = {}  # topic -> foxglove.Channel
        for topic in (TOPIC_STATE, TOPIC_TRANSFORM, TOPIC_SCENE, TOPIC_EVENTS, TOPIC_LOG):
            name, encoding, message_encoding = CHANNELS[topic]
            schema = foxglove.Schema(name=name, encoding=encoding, data=schema_bytes(name))
            self._channels[topic] = foxglove.Channel(topic, schema=schema, context=self.context,
                                                     message_encoding=message_encoding)
        for topic, js in _JSON_SCHEMAS.items():
            self._channels[topic] = self._json_channel(topic, js["title"], js)
        self._channels[TOPIC_TILT] = self._json_channel(
            TOPIC_TILT, "foxglove.SceneUpdate", json.loads(schema_bytes("foxglove.SceneUpdate")))
        self._last_scene = 0.0
        self._health_poses = -1
        self._queue: deque[WrittenViews] = deque()
        self._queued = 0  # messages in the queue
        self._queue_lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = False
        #: per-scan view messages dropped from the queue (it was full), and handed to the
        #: server while someone subscribed
        self.dropped = 0
        self.served = 0
        self._thread = threading.Thread(target=self._serve, name="loopcal-live", daemon=True)
        self._thread.start()
        if what := exposed(host):
            log.warning("the live view on %s is served to %s, not only to this machine: "
                        "anyone who reaches it watches the session (read-only); bind "
                        "127.0.0.1 and reach it through an SSH tunnel (docs/tools.md)",
                        self.url, what)  # fmt: skip
        log.info("live view: %s (Foxglove: open a connection, Foxglove WebSocket)", self.url)

    def _json_channel(self, topic: str, name: str, js: dict[str, Any]) -> Any:
        fx = self._fx
        schema = fx.Schema(name=name, encoding="jsonschema", data=json.dumps(js).encode())
        return fx.Channel(topic, schema=schema, context=self.context, message_encoding="json")

    def _log(self, topic: str, data: bytes | str, log_time: int) -> None:
        self._channels[topic].log(data, log_time=int(log_time))

    # ------------------------------------------------------------------ scan views

    def views(self, views: WrittenViews) -> None:
        """The views of scans the recording's writer has just written (its thread): queued
        for the live view's thread. Returns at once; past :data:`QUEUE` messages waiting,
        the oldest are dropped and counted in :attr:`dropped`."""
        if not len(views):
            return
        with self._queue_lock:
            self._queue.append(views)
            self._queued += len(views)
            while self._queued > QUEUE:
                old = self._queue.popleft()
                self._queued -= len(old)
                if self._queued < QUEUE:  # keep the newest messages of the oldest write
                    kept = _newest(old, QUEUE - self._queued)
                    self._queue.appendleft(kept)
                    self._queued += len(kept)
                    self.dropped += len(old) - len(kept)
                else:
                    self.dropped += len(old)
        self._wake.set()

    def _serve(self) -> None:
        """The live view's thread: hands the queued views to the server (to subscribers)."""
        state, transform = (self._channels[t].base for t in (TOPIC_STATE, TOPIC_TRANSFORM))
        while not self._closing:
            self._wake.wait()
            self._wake.clear()
            with self._queue_lock:
                pending, self._queue = self._queue, deque()
                self._queued = 0
            for v in pending:
                for base, stamps, messages in ((state, v.state_stamps, v.states),
                                               (transform, v.transform_stamps, v.transforms)):
                    if messages and base.has_sinks():
                        for t, data in zip(stamps.tolist(), messages, strict=True):
                            base.log(data, t, None)
                        self.served += len(messages)
            if pending:
                last = pending[-1]
                self._scene(int(max(last.state_stamps[-1:].tolist()
                                    + last.transform_stamps[-1:].tolist())))

    def _scene(self, stamp_ns: int) -> None:
        """/plate/scene, every :data:`SCENE_EVERY_S` while someone subscribes."""
        now = time.monotonic()
        ch = self._channels[TOPIC_SCENE]
        if now - self._last_scene >= SCENE_EVERY_S and ch.has_sinks():
            ch.log(scene_message(stamp_ns, self.params), log_time=stamp_ns)
            self._last_scene = now

    def metrics(self) -> Iterator[Any]:
        """The live view's counters for the recorder's metrics."""
        yield CounterMetricFamily(
            "loopcal_live_dropped_messages", "live view messages (per-scan views) dropped "
            "because the live view's queue was full; not those the server drops for a "
            "client that cannot keep up", value=self.dropped)  # fmt: skip
        yield CounterMetricFamily(
            "loopcal_live_messages", "per-scan view messages handed to the live view's "
            "server while someone subscribed", value=self.served)  # fmt: skip

    # ------------------------------------------------------------------ observer

    def feed(self, rows: np.ndarray) -> None:
        """After the health monitor's feed (the analysis thread): its latest test, if new.
        The scans' views come from the recording's writer (:meth:`views`)."""
        self._publish_health()

    def _publish_health(self) -> None:
        h = self.health
        if h is None or h.state.poses == self._health_poses:
            return
        self._health_poses = h.state.poses
        st, now = h.state, time.time_ns()
        doc: dict[str, Any] = {"timestamp": _stamp(now), "poses": st.poses,
                               "threshold": float(h.threshold),
                               "alarm_sensor": st.alarm_sensor or 0,
                               "loops_open": st.open_since_start, "status": h.status()}
        if st.last is not None:
            doc.update(statistic=[float(x) for x in st.last.statistic],
                       shift_mm=[float(x) for x in st.last.shift_mm],
                       std_mm=[float(x) for x in st.last.std_mm])  # fmt: skip
        self._log(TOPIC_HEALTH, json.dumps(doc), now)

    def status(self) -> str:
        return f"live view {self.url}"

    def reload(self, controller: ControllerConfig) -> None:
        self.params = np.array(controller.params, dtype=float)

    # ------------------------------------------------------------------ other sources

    def event(self, ev: Event) -> None:
        """An event as the recorder emits it (any thread): /loopcal/events and /loopcal/log."""
        obj = ev.to_json()
        with self._lock:
            self._log(TOPIC_EVENTS, json.dumps(obj), ev.stamp_ns)
            self._log(TOPIC_LOG, json.dumps(log_entry(ev, obj)), ev.stamp_ns)

    def guidance(self, update: GuidanceUpdate) -> None:
        """A guidance update: the collection so far, and the next tilt drawn in the 3D scene
        as an arrow from the base's centre towards the base point of the sensor whose side
        the plate has reached least (none once enough)."""
        now = time.time_ns()
        doc = {k: v for k, v in update.as_json().items()
               if k in _JSON_SCHEMAS[TOPIC_GUIDANCE]["properties"]}  # fmt: skip
        doc["reach_deg"] = [round(float(r), 1) for r in update.reach_deg]
        doc["twist_deg"] = [round(float(t), 1) for t in update.twist_deg]  # clockwise, ccw
        self._log(TOPIC_GUIDANCE, json.dumps(doc), now)
        entities = []
        if not update.enough and len(update.reach_deg):
            sensor = int(np.argmin(update.reach_deg))
            x, y = base_points(self.params)[sensor][:2]
            half = float(np.arctan2(y, x)) / 2  # the arrow's +x turned towards A(sensor)
            arrow = {
                "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                         "orientation": {"x": 0.0, "y": 0.0, "z": float(np.sin(half)),
                                         "w": float(np.cos(half))}},
                "shaft_length": 0.08, "shaft_diameter": 0.006, "head_length": 0.025,
                "head_diameter": 0.016, "color": {"r": 1.0, "g": 0.5, "b": 0.0, "a": 1.0},
            }  # fmt: skip
            entity = {"timestamp": _stamp(now), "frame_id": BASE_FRAME, "id": "next-tilt",
                      "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False,
                      "metadata": [{"key": "sensor", "value": str(sensor + 1)}]}  # fmt: skip
            for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles",
                         "texts", "models"):  # fmt: skip
                entity[kind] = [arrow] if kind == "arrows" else []
            entities.append(entity)
        scene = {"deletions": [{"timestamp": _stamp(now), "type": 1, "id": ""}],
                 "entities": entities}  # fmt: skip
        self._log(TOPIC_TILT, json.dumps(scene), now)

    def close(self) -> None:
        self._closing = True
        self._wake.set()
        self._thread.join(5.0)
        self.server.stop()


def watch_live(recorder: Any, listen: str | None, *, health: HealthMonitor | None = None
               ) -> LiveView | None:  # fmt: skip
    """Serve the recorder's live view on ``listen`` (None: no live view): an observer of its
    scans and a listener of its events; returns it (close it when the recorder stops). The
    address is the one in force at start: a reload does not move or start the live view."""
    if listen is None:
        return None
    view = LiveView(listen, recorder.controller, health=health)
    recorder.add_observer(view)
    recorder.event_listeners.append(view.event)
    recorder.view_listeners.append(view.views)
    return view


def _newest(v: WrittenViews, keep: int) -> WrittenViews:
    """The newest ``keep`` messages of ``v`` (of each channel in proportion)."""
    n = len(v)
    ks = keep * len(v.states) // n if n else 0
    kt = keep - ks
    return WrittenViews(v.state_stamps[len(v.states) - ks:], v.states[len(v.states) - ks:],
                        v.transform_stamps[len(v.transforms) - kt:],
                        v.transforms[len(v.transforms) - kt:])  # fmt: skip
