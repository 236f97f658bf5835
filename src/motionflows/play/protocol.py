"""The page <-> server socket protocol: JSON text messages, checked and clamped here.

Page -> server (one JSON object per message, at most ``MAX_MESSAGE_BYTES``)::

    {"type": "control", "forward": m/s, "sideways": m/s, "turn": rad/s,
     "seq": int, "sent": page clock ms}          the target control (ramped by the server)
    {"type": "pause", "paused": bool}
    {"type": "reset"}                             back to standing at the origin
    {"type": "temperature", "value": float}

Server -> page: ``hello`` (skeleton, fps, limits; once), ``frame`` (one per model frame:
world joints, root, control, timings, the ``ack`` of the last control applied with its
``sent`` time echoed, so the page measures key-to-frame latency on its own clock),
``error`` (a message was rejected; the stream goes on) and ``busy`` (another page holds
the character; the socket then closes with code ``BUSY_CLOSE_CODE``).

Values outside the limits are clamped (a game pad or a typo never throws the character
across the floor); anything that is not a message of the table is rejected with a reason.
"""

from __future__ import annotations

import json
import math
from typing import Any

MAX_MESSAGE_BYTES = 4096
LIMITS = {"forward": (-1.5, 3.5), "sideways": (-1.5, 1.5), "turn": (-math.pi, math.pi)}
"""Target control limits: m/s, m/s (+ = left), rad/s (+ = counter-clockwise)."""
TEMPERATURE_RANGE = (0.0, 1.5)
BUSY_CLOSE_CODE = 4409


class BadMessage(ValueError):
    """A socket message that is not part of the protocol (the reason is sent back)."""


def _number(msg: dict, name: str, lo: float, hi: float, default: float | None = None) -> float:
    value = msg.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise BadMessage(f"{name!r} must be a number, got {type(value).__name__}")
    try:
        value = float(value)
    except OverflowError:  # an integer beyond float range
        value = math.inf if value > 0 else -math.inf
    if math.isnan(value):
        raise BadMessage(f"{name!r} is NaN")
    return min(max(value, lo), hi)  # +-inf clamp to the limits


def parse_message(raw: str | bytes | None) -> dict[str, Any]:
    """One page message -> a checked command dict (numbers clamped to the limits).

    Raises ``BadMessage`` naming the problem for binary, oversized, non-JSON, non-object,
    unknown-type or wrongly typed messages.
    """
    if not isinstance(raw, str):
        raise BadMessage("messages are JSON text, not binary")
    if len(raw) > MAX_MESSAGE_BYTES:
        raise BadMessage(f"message of {len(raw)} characters (at most {MAX_MESSAGE_BYTES})")
    try:
        msg = json.loads(raw)
    except (ValueError, RecursionError):
        raise BadMessage("not JSON") from None
    if not isinstance(msg, dict):
        raise BadMessage("a message is a JSON object with a 'type'")
    kind = msg.get("type")
    if kind == "control":
        seq = msg.get("seq", 0)
        sent = msg.get("sent", 0.0)
        if isinstance(seq, bool) or not isinstance(seq, int):
            raise BadMessage("'seq' must be an integer")
        if isinstance(sent, bool) or not isinstance(sent, int | float) or not math.isfinite(sent):
            raise BadMessage("'sent' must be a finite number (page clock, ms)")
        return {
            "type": "control",
            "target": tuple(_number(msg, k, *LIMITS[k], default=0.0) for k in LIMITS),
            "seq": seq,
            "sent": float(sent),
        }
    if kind == "pause":
        paused = msg.get("paused")
        if not isinstance(paused, bool):
            raise BadMessage("'paused' must be true or false")
        return {"type": "pause", "paused": paused}
    if kind == "reset":
        return {"type": "reset"}
    if kind == "temperature":
        return {"type": "temperature", "value": _number(msg, "value", *TEMPERATURE_RANGE)}
    raise BadMessage(f"unknown message type {str(kind)[:40]!r}")
