"""The ``[transports.zenoh]`` table and the zenoh ``Config`` built from it.

The table covers what a fleet usually sets (mode, endpoints, multicast scouting); anything more
(TLS/mTLS, access control, shared memory, timeouts) goes in a zenoh config file named by
``config_file``. Precedence: keys set in the table override the file (a key set in both must
agree: ``check_files`` refuses a conflict, :func:`mapd.ros2.zenoh_config.table_conflicts`); keys
left out keep the file's value, or zenoh's default when there is no file. mapd always caps zenoh's largest accepted
message at ``limits.max_message_bytes`` plus a margin, so a peer cannot make zenoh allocate a
huge message for mapd to refuse afterwards. zenoh drops a larger one without a word, so a peer's
map past the cap is neither counted nor said here; one between the limit and the cap is refused
and said once per robot (``oversize_rx``). On one host zenoh may carry large messages in shared
memory, past the cap: those reach mapd and are refused and said the same way.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Literal

from pydantic import Field

from mapd.config.endpoints import ZenohEndpoints
from mapd.errors import TransportError
from mapd.ros2.zenoh_config import ZenohConfigFiles, zenoh_config_text, zenoh_message
from transports.base import TransportOptions

# Room for zenoh's own framing around an envelope of max_message_bytes.
_RX_MARGIN = 64 * 1024


class ZenohOptions(ZenohEndpoints, ZenohConfigFiles, TransportOptions):
    """Options of the ``zenoh`` transport."""

    mode: Literal["peer", "client", "router"] = Field(
        default="peer", description="zenoh mode: peer (no server), client (via a router), or router"
    )
    listen: list[str] = Field(
        default_factory=list,
        description="endpoints to listen on, e.g. tcp/0.0.0.0:7447; empty: zenoh default",
    )
    connect: list[str] = Field(
        default_factory=list, description="endpoints to connect to (peers or routers), e.g. tcp/10.0.0.2:7447"
    )
    multicast_scouting: bool = Field(default=True, description="find peers on the LAN by UDP multicast")
    config_file: Path | None = Field(
        default=None, description="zenoh JSON5 config for anything more (TLS/mTLS, access control)"
    )
    query_timeout_s: float = Field(
        default=2.0, gt=0.0, le=60.0, description="how long a keyframe query waits for replies"
    )
    close_timeout_s: float = Field(
        default=1.0, gt=0.0, le=10.0, description="longest close() waits for zenoh before giving up"
    )
    congestion: Literal["block", "drop"] = Field(
        default="block",
        description="when zenoh's send queue is full: block the sender thread (a newer offer still replaces"
        " the pending one) or let zenoh drop the message (receivers then recover by query)",
    )
    pose_period_s: float = Field(
        default=0.5, ge=0.0, description="seconds between this robot's pose messages (0: send none)"
    )
    base_window: int = Field(
        default=8, ge=1, le=1024, description="recent versions per peer accepted as a delta base"
    )
    max_peers: int = Field(default=64, ge=1, le=4096, description="robots tracked at once")
    max_pending: int = Field(
        default=256, ge=8, le=65536, description="zenoh operations (acks, queries, replies) waiting at once"
    )


def build_config(options: ZenohOptions, max_message_bytes: int) -> object:
    """A ``zenoh.Config`` for ``options``; :class:`TransportError` with one line when it cannot be."""
    import zenoh  # imported here so that `mapd` works without the optional dependency

    explicit = options.model_fields_set
    if options.config_file is not None:
        try:
            # Read by mapd, not zenoh.Config.from_file: a FIFO or /dev/zero named here hung the daemon.
            conf = zenoh.Config.from_json5(zenoh_config_text(options.config_file))
        except (zenoh.ZError, ValueError) as exc:
            raise TransportError(
                f"zenoh: cannot use config file {options.config_file}: {zenoh_message(exc)}"
            ) from None
    else:
        conf = zenoh.Config()

    def want(name: str) -> bool:
        # Without a file, defaults are applied too (they are zenoh's defaults made explicit).
        return options.config_file is None or name in explicit

    settings: list[tuple[str, str]] = []
    if want("mode"):
        settings.append(("mode", json.dumps(options.mode)))
    if want("listen") and options.listen:
        settings.append(("listen/endpoints", json.dumps(options.listen)))
    if want("connect") and options.connect:
        settings.append(("connect/endpoints", json.dumps(options.connect)))
    if want("multicast_scouting"):
        settings.append(("scouting/multicast/enabled", json.dumps(options.multicast_scouting)))
    cap = max_message_bytes + _RX_MARGIN
    with contextlib.suppress(zenoh.ZError, ValueError, TypeError):
        # A file may set a lower cap still; keep the smaller one.
        cap = min(cap, int(json.loads(conf.get_json("transport/link/rx/max_message_size"))))
    settings.append(("transport/link/rx/max_message_size", str(cap)))
    for key, value in settings:
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as exc:
            raise TransportError(f"zenoh: bad setting {key} = {value}: {zenoh_message(exc)}") from None
    return conf
