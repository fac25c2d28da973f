"""The links' health as ROS 2 diagnostics: ``diagnostic_msgs/msg/DiagnosticArray`` in CDR.

What ``diagnostic_updater`` publishes on ``/diagnostics``, so the tools made for it read mapd's
links as they read a robot's drivers: Foxglove's *Diagnostics* panel, ``rqt_robot_monitor``
behind a ``diagnostic_aggregator``, and ``ros2 bag`` (whose reader refuses a recording with one
channel in another encoding: the counters were JSON before). One :class:`Diagnostic` per link:
its level (``OK``, or ``WARN`` while ``mapd status`` shows a fault on it), the faults in words as
its message, and every counter as a key/value pair (nested tables as dotted keys, lists as JSON).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

#: The message type, and its levels (``DiagnosticStatus`` constants).
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
OK, WARN = 0, 1
#: The topic ``diagnostic_updater`` publishes on (absolute: diagnostics are not namespaced).
DIAGNOSTICS_TOPIC = "/diagnostics"
#: Key/value pairs kept per status: a link's counters are a few dozen; a value cut to this length.
MAX_VALUES = 256
MAX_VALUE_CHARS = 1024


@dataclass(frozen=True)
class Diagnostic:
    """One ``DiagnosticStatus``."""

    name: str
    level: int
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...] = ()


def flat_values(doc: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """``doc``'s leaves as (dotted key, text) pairs, sorted by key; at most :data:`MAX_VALUES`.

    Text is what an operator reads: strings as they are, numbers and booleans as JSON writes them
    (``true``, ``12.5``), lists and other values as JSON."""
    out: list[tuple[str, str]] = []

    def walk(d: Mapping[str, Any], pre: str) -> None:
        for k in sorted(d, key=str):
            v, key = d[k], f"{pre}{k}"
            if isinstance(v, Mapping) and v:
                walk(v, key + ".")
            else:
                text = v if isinstance(v, str) else json.dumps(v, default=str, sort_keys=True)
                out.append((key, text[:MAX_VALUE_CHARS]))

    walk(doc, prefix)
    return out[:MAX_VALUES]


def encode_diagnostics(statuses: Iterable[Diagnostic], stamp: float) -> bytes:
    """A CDR ``DiagnosticArray`` of ``statuses`` stamped ``stamp`` (wall clock, seconds)."""
    from mapd.ros2.cdr import split_stamp, typestore

    ts = typestore()
    t = ts.types
    msg = t[DIAGNOSTICS_TYPE](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](*split_stamp(stamp)), frame_id=""
        ),
        status=[
            t["diagnostic_msgs/msg/DiagnosticStatus"](
                level=d.level,
                name=d.name,
                message=d.message,
                hardware_id=d.hardware_id,
                values=[t["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in d.values],
            )
            for d in statuses
        ],
    )
    return bytes(ts.serialize_cdr(msg, DIAGNOSTICS_TYPE))
