"""What ``mapd status`` shows: the running daemon's parts read into one JSON-able dict.

The control socket (:mod:`~mapd.daemon.status_socket`), the live view, the systemd Status line
(:mod:`~mapd.daemon.headline`) and the recording all read this one dict, so each says the same.
It is read on the event loop's thread and only reads counters: it never waits.
"""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mapd.daemon.server import Daemon


def snapshot(d: Daemon) -> dict[str, Any]:
    """Everything ``mapd status`` shows of daemon ``d``, as JSON-able data."""
    now = time.time()
    own = d.own
    pub = d.publisher.counters
    return {
        "robot": d.me,
        "fleet": d.cfg.robot.fleet,
        "pid": os.getpid(),
        "uptime_s": round(now - d.started, 1),
        "loop": d.loop_lag.stats(time.monotonic()),
        "source": {
            "name": d.cfg.source.use,
            "version": own.version if own else 0,
            "size": [own.width, own.height] if own else None,
            "finished": d.outbound.source_finished,
            # its newest maps skipped (over limits.max_cells, or unsendable): not shared, not fused
            "skipped": (
                {"why": d.outbound.skipped, "maps": d.outbound.skipped_maps} if d.outbound.skipped else None
            ),
            "stats": d.source.stats() if d.source else {},
        },
        "codec": {
            **d.coder.stats,
            "keyframes": pub.keyframes_sent,
            "deltas": pub.deltas_sent,
            "reoffers": pub.reoffers,
            "failed": dict(pub.failed),  # per link: offers that could not reach a peer (P7)
        },
        "offers": d.publisher.offers(time.monotonic()),
        "peers": d.receiver.status(now, d.store.acked()),
        "links": {t.name: {**t.stats(), "peers": t.peers()} for t in d.transports},
        "outputs": d.sinks.status(),
        "recording": d.sinks.recording(),
        "fusion": d.fusion.status(),
        "poses": d.poses.status(now),
        "counters": {
            **vars(d.receiver.counters),
            "keyframes_sent": pub.keyframes_sent,
            "deltas_sent": pub.deltas_sent,
            # a flood: older updates replaced by newer ones before decoding, or events dropped
            "superseded_updates": d.events.counters.superseded,
            "dropped_events": d.events.counters.dropped,
        },
        "security": {
            "signed": d.keys.signed,
            "public_key": d.keys.identity.public_text if d.keys.identity else None,
            "roster": d.keys.roster.robots,
            "link_key": d.keys.link_key is not None,
        },
        "reload": d.reloads.status(),
        "state_dir": str(d.cfg.state.dir),
        # Saves that fail now (a full disk): the state's, and the global map's beside it.
        "state": {
            **d.store.health(),
            "global_map": d.fusion.store.health() if d.fusion.store is not None else None,
        },
    }
