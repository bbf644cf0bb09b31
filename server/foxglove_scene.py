"""A Foxglove 3D channel for a finished campaign archive: the neck as ``foxglove.SceneUpdate``.

The recorder writes the bus's own messages (JSON + JSON Schema, which Foxglove plots). For its
3D panel Foxglove needs one of its own schemas, so when a campaign ends the console rewrites the
archive once with an extra topic ``/xneck/scene``: at ``rate_hz`` (of log time), a SceneUpdate
whose entity ``neck`` (frame ``base``, y up, metres) holds line lists of the bars, springs,
pulleys, each cable coloured by tension, and the bars at α^d (green ghost). The pose is α̂ from
``/xneck/controller/status`` (or the twin's truth when there is no controller status).

Schema: JSON encoding of Foxglove's documented ``foxglove.SceneUpdate`` message (deletions,
entities → SceneEntity with timestamp {sec, nsec}, frame_id, id, lifetime, frame_locked,
metadata and primitive lists; lines → LinePrimitive with type 2 = LINE_LIST, pose, thickness,
scale_invariant, points {x, y, z}, color {r, g, b, a}, colors, indices). Only the fields used here
are spelled out in the JSON Schema; Foxglove selects the decoder by the schema name.

The rewrite goes to a temporary file that atomically replaces the archive: a crash leaves the
original intact.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from mcap.reader import SeekingReader
from mcap.writer import Writer

from bridge import bus
from server.archive_rewrite import OnMessage, rewrite_archive
from server.neck_geometry import NeckDrawing, tension_colors
from twin.model.params import Params

SCENE_TOPIC = "/xneck/scene"
SCHEMA_NAME = "foxglove.SceneUpdate"
FRAME_ID = "base"
METADATA = "xneck.foxglove"

_vec3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_quat = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_color = {"type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}
_time = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_line = {
    "type": "object", "title": "foxglove.LinePrimitive",
    "properties": {
        "type": {"type": "integer", "description": "0 LINE_STRIP, 1 LINE_LOOP, 2 LINE_LIST"},
        "pose": {"type": "object", "properties": {"position": _vec3, "orientation": _quat}},
        "thickness": {"type": "number"}, "scale_invariant": {"type": "boolean"},
        "points": {"type": "array", "items": _vec3}, "color": _color,
        "colors": {"type": "array", "items": _color}, "indices": {"type": "array", "items": {"type": "integer"}},
    },
}
_entity = {
    "type": "object", "title": "foxglove.SceneEntity",
    "properties": {
        "timestamp": _time, "frame_id": {"type": "string"}, "id": {"type": "string"}, "lifetime": _time,
        "frame_locked": {"type": "boolean"},
        "metadata": {"type": "array", "items": {"type": "object", "properties": {
            "key": {"type": "string"}, "value": {"type": "string"}}}},
        **{k: {"type": "array", "items": {"type": "object"}} for k in
           ("arrows", "cubes", "spheres", "cylinders", "triangles", "texts", "models")},
        "lines": {"type": "array", "items": _line},
    },
}
SCENE_UPDATE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": SCHEMA_NAME,
    "description": "An update to the entities displayed in a 3D scene (Foxglove schema, JSON encoding)",
    "type": "object",
    "properties": {
        "deletions": {"type": "array", "items": {"type": "object"}},
        "entities": {"type": "array", "items": _entity},
    },
}

_IDENTITY = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def _rgba(rgb: np.ndarray | tuple[int, int, int], a: float = 1.0) -> dict[str, float]:
    r, g, b = (float(c) / 255.0 for c in rgb)
    return {"r": r, "g": g, "b": b, "a": a}


def _line_list(segments: np.ndarray, rgb, thickness_m: float, a: float = 1.0) -> dict[str, Any]:
    pts = segments.reshape(-1, 3)
    return {"type": 2, "pose": _IDENTITY, "thickness": thickness_m, "scale_invariant": False,
            "points": [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in pts],
            "color": _rgba(rgb, a), "colors": [], "indices": []}


def scene_update(drawing: NeckDrawing, alpha: np.ndarray, alpha_d: np.ndarray | None,
                 tension_N: np.ndarray | None, f_max_N: float, time_ns: int) -> dict[str, Any]:
    """One SceneUpdate (JSON-ready dict) of the neck at ``alpha`` (rad)."""
    g = drawing.geometry(alpha)
    lines = [_line_list(g.bars, (40, 40, 48), 0.004), _line_list(g.springs, (150, 150, 160), 0.0015),
             _line_list(g.pulleys, (90, 90, 110), 0.001)]
    colors = tension_colors(tension_N, f_max_N) if tension_N is not None else None
    for j, segs in enumerate(g.cables):
        lines.append(_line_list(segs + np.array([0.0, 0.0, 0.002 * (j + 1)]),
                                colors[j] if colors is not None else (0, 0, 255), 0.002))
    if alpha_d is not None:
        lines.append(_line_list(drawing.skeleton(alpha_d), (40, 170, 80), 0.002, 0.6))
    stamp = {"sec": time_ns // 1_000_000_000, "nsec": time_ns % 1_000_000_000}
    entity = {"timestamp": stamp, "frame_id": FRAME_ID, "id": "neck", "lifetime": {"sec": 0, "nsec": 0},
              "frame_locked": False, "metadata": [], "arrows": [], "cubes": [], "spheres": [], "cylinders": [],
              "lines": lines, "triangles": [], "texts": [], "models": []}
    return {"deletions": [], "entities": [entity]}


def add_scene_channel(path: str | os.PathLike[str], params: Params, rate_hz: float = 20.0) -> int:
    """Rewrite the finished archive ``path`` with a ``/xneck/scene`` channel; returns the number
    of scene messages added (0, and the file untouched, if there is no pose to draw or it already
    has one)."""
    path = Path(path)
    drawing = NeckDrawing(params)
    f_max = float(params.limits.f_max)
    status_topic, truth_topic = bus.mcap_topic(bus.CONTROLLER_STATUS), bus.mcap_topic(bus.TWIN_TRUTH)
    with open(path, "rb") as f:
        summary = SeekingReader(f).get_summary()
        topics = {c.topic for c in summary.channels.values()} if summary else set()
    if SCENE_TOPIC in topics or not ({status_topic, truth_topic} & topics):
        return 0
    pose_topic = status_topic if status_topic in topics else truth_topic
    period_ns = int(1e9 / rate_hz)
    state: dict[str, Any] = {"added": 0, "next_ns": 0, "tension": None, "truth": None}

    def begin(writer: Writer) -> OnMessage:
        scene_schema = writer.register_schema(SCHEMA_NAME, "jsonschema", json.dumps(SCENE_UPDATE_SCHEMA).encode())
        scene_channel = writer.register_channel(SCENE_TOPIC, "json", scene_schema, {"frame_id": FRAME_ID})

        def after(writer: Writer, _schema, channel, message) -> None:
            if channel.topic == truth_topic:
                # Decoded when a scene is drawn only: every truth at 500 Hz took 11 s of a 600 s campaign.
                state["truth"] = message.data
            if channel.topic == pose_topic and message.log_time >= state["next_ns"]:
                if state["truth"] is not None:
                    state["tension"] = np.asarray(msgspec.json.decode(state["truth"])["tension_N"], dtype=float)
                    state["truth"] = None
                doc = msgspec.json.decode(message.data)
                if pose_topic == status_topic:
                    alpha, alpha_d = doc["alpha_hat_rad"], doc["alpha_d_rad"]
                else:
                    alpha, alpha_d = doc["alpha_rad"], None
                update = scene_update(drawing, np.asarray(alpha), None if alpha_d is None else np.asarray(alpha_d),
                                      state["tension"], f_max, message.log_time)
                writer.add_message(scene_channel, message.log_time, msgspec.json.encode(update),
                                   message.log_time, state["added"])
                state["added"] += 1
                state["next_ns"] = message.log_time + period_ns

        return after

    def end(writer: Writer) -> None:
        writer.add_metadata(METADATA, {"scene_topic": SCENE_TOPIC, "frame_id": FRAME_ID, "rate_hz": str(rate_hz),
                                       "source_topic": pose_topic, "messages": str(state["added"])})

    rewrite_archive(path, begin=begin, end=end)
    added = state["added"]
    return added
