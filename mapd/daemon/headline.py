"""The daemon's state in one line, and the link faults worth saying: for ``systemctl status`` and
``mapd status``.

Under systemd the daemon sends this line as ``STATUS=`` (sd_notify), so ``systemctl status mapd``
shows what the robot is doing (its map, its peers', the global map, and any fault) without
``mapd status``; the fault words are the ones ``mapd status`` prints on its ``FAULTS`` lines.
Pure functions of a status document (:meth:`Daemon.snapshot`), so both read the same facts.
"""

from __future__ import annotations

from typing import Any

from mapd.daemon.loop_lag import SAY_S, cause, finite
from mapd.daemon.versions import label

#: A link's figures that mean something is wrong when not zero (``port_open``, ``session_open``
#: and ``clock_synchronized``: when false).
LINK_FAULTS = {
    "port_open": "serial port closed (reopening)",
    "session_open": "zenoh session not open yet (trying again)",
    # a session that lost its router(s) later: zenoh reconnects by itself (None: peers, no router)
    "router_connected": "router lost (zenoh reconnects by itself)",
    # an output's tries that a router answered and refused (it keeps trying: see outputs.zenoh)
    "session_refusals": "{} session tries refused by the router (its certificate, ACL or version?)",
    "clock_synchronized": "wall clock not synchronized (TDMA turns need it: chrony)",
    # peers' maps refused unread for their size (zenoh): config drift, said with the robot and size
    "oversize_rx": "{} peer maps over this robot's limits.max_message_bytes refused (the log names the robot)",
    # zenoh: peers that announced a smaller limits.max_message_bytes than our maps (config drift;
    # they get none of them); the peers and sizes: the link's too_big_for (too_big_words)
    "too_big_peers": "{} peers take smaller messages than this robot's maps (their limits.max_message_bytes)",
    "reconnects": "port reopened {} times",
    "write_stalls": "port took no bytes {} times",
    "counter_save_errors": "signing counter not saved {} times (disk full or read-only?)",
    "replay_save_errors": "replay marks not saved {} times (disk full or read-only?)",
    # an output that writes files (``files``): False while its newest map cannot be written
    "writing": "not writing (disk full?)",
    "out_of_turn": "{} frames of others on the air in this robot's own TDMA slot (do the clocks agree?)",
    # A counter over 5 minutes ahead of this clock: clocks far apart, or a link-key holder's forgery.
    "future": "{} frames signed with counters over 5 min ahead of this robot's clock (clocks apart, or a forged link key?)",
    # The frame's link tag was good but the robot key was not: whoever sent it holds the link key.
    "keyframe_requests_forged": "{} keyframe requests in another robot's name (has the link key leaked?)",
    # uwb: peers whose radio acks our maps while their daemon holds none (their relay summaries
    # say so); their log and mapd status say why (config drift). The peers: the link's refused_by.
    "refused_by_peers": "{} peers ack this robot's maps at the radio but their daemons refuse them (the log names them; their mapd status says why)",
}

#: A serial link's frames that arrived damaged, by what caught them: COBS, the length (no delimiter
#: within ``max_frame``), a frame too short, the CRC or, on a keyed link (whose tag replaces the CRC),
#: the tag. A wrong ``baud`` or a noisy cable raises these and nothing else.
DAMAGE_KEYS = ("crc_errors", "cobs_errors", "oversize", "runts", "bad_signature")
#: The keys only a serial framing reports (a zenoh link's ``bad_signature`` is a forged map, not damage).
_FRAMING_KEYS = DAMAGE_KEYS[:4]

#: Counters of messages a link without serial framing (zenoh) refused before the daemon saw them,
#: for a reason the roster fixes: a robot off it (``unadmitted``), or a signature its keys refuse
#: (``bad_signature``: a key there that is old, an ack of a robot off it, or a forgery).
ROSTER_REFUSALS = ("unadmitted", "bad_signature")

#: systemd shows STATUS= on one line of ``systemctl status``: keep it to what fits there.
MAX_LINE = 200


def _count(v: Any) -> int:
    return v if isinstance(v, int) and not isinstance(v, bool) and v > 0 else 0


def damaged(st: dict[str, Any]) -> int | None:
    """Frames the line delivered damaged (the uwb link's ``damaged``: the sum of
    :data:`DAMAGE_KEYS`); None for a link without serial framing."""
    v = st.get("damaged")
    return _count(v) if isinstance(v, int) else None


def damage_words(st: dict[str, Any]) -> str | None:
    """``damaged=16 (cobs_errors=11 oversize=5)`` for ``mapd status`` and ``mapd link``: the total,
    then what caught them; None for a link without serial framing."""
    total = damaged(st)
    if total is None:
        return None
    parts = [f"{k}={st[k]}" for k in DAMAGE_KEYS if _count(st.get(k))]
    return f"damaged={total}" + (f" ({' '.join(parts)})" if parts else "")


def _damage_fault(st: dict[str, Any]) -> str | None:
    """Damaged frames since the last valid one while no peer is heard: what a wrong baud, a noisy
    cable or another link key looks like (the peer would otherwise merely look gone, out of range).
    Damage from before a valid frame came is not counted: a robot alone now, out of its peers'
    range, with some noise long past, is not at fault. Said as a question, with the facts it rests
    on."""
    total = _count(st.get("damaged_since_valid"))
    if not total or st.get("peers_up") != 0 or st.get("port_open") is False:
        return None
    if not any(_count(st.get(k)) for k in _FRAMING_KEYS):  # every frame whole, but the tag fails
        return f"{total} frames failed the link tag, no peer heard (another link key, or a noisy line?)"
    return f"{total} damaged frames, no peer heard (wrong baud or noisy line?)"


def link_faults(st: dict[str, Any]) -> list[str]:
    """The link's faults worth a line in ``mapd status``, in words."""
    out = []
    for k, words in LINK_FAULTS.items():
        v = st.get(k)
        if "{}" not in words:  # a state, at fault when false (port_open, session_open, ...)
            if v is False:
                out.append(words)
        elif isinstance(v, int) and not isinstance(v, bool) and v > 0:
            out.append(words.format(v))
    if (damage := _damage_fault(st)) is not None:
        out.append(damage)
    if refused := roster_refusals(st):
        out.append(
            f"{refused} messages refused by this roster (a robot's key missing there, or old; or forged?)"
        )
    return out


def roster_refusals(st: dict[str, Any]) -> int:
    """Messages a link without serial framing refused for the roster (:data:`ROSTER_REFUSALS`); 0
    for a serial link, whose ``bad_signature`` counts frames the line damaged."""
    if "damaged" in st:
        return 0
    return sum(_count(st.get(k)) for k in ROSTER_REFUSALS)


def peer_faults(s: dict[str, Any]) -> list[str]:
    """What the peers' entries of a status document say is wrong between this robot's config and
    theirs (:mod:`mapd.daemon.receiver`: a refusal, a peer taking none of our maps, a link that knows
    a robot by a name the roster does not), in words."""
    out = []
    for name, p in (s.get("peers") or {}).items():
        if not isinstance(p, dict):
            continue
        refused = p.get("refused")
        if isinstance(refused, dict):
            out.append(f"maps of {name} refused ({refused.get('why')})")
        if p.get("takes_ours") is False:
            out.append(f"{name} takes none of this robot's maps")
        if isinstance(p.get("heard_as"), str):
            out.append(f"{name} heard as '{p['heard_as']}' (nodes lists differ?)")
    return out


def state_faults(s: dict[str, Any]) -> list[str]:
    """The state directory's saves that fail now (a full disk), in words; [] when they go through."""
    st = s.get("state")
    if not isinstance(st, dict):
        return []
    out = []
    if st.get("writing") is False:
        out.append("state dir not writable (disk full, read-only or gone?): own maps held back")
    g = st.get("global_map")
    if isinstance(g, dict) and g.get("writing") is False:
        out.append("global map not saved")
    return out


def loop_held(s: dict[str, Any]) -> float | None:
    """How long the event loop was last held (s), when that was a hold of a second or more (one the
    daemon logs: :data:`mapd.daemon.loop_lag.SAY_S`) within the loop's recent window; else None."""
    lp = s.get("loop")
    if not isinstance(lp, dict):
        return None
    last, ago, recent = (finite(lp.get(k)) for k in ("last_stall_ms", "last_stall_ago_s", "recent_s"))
    if last is None or ago is None or recent is None:
        return None
    return last / 1000 if last >= SAY_S * 1000 and 0 <= ago < recent else None


def loop_cause(s: dict[str, Any]) -> str | None:
    """Why the loop's last stall held it (:func:`mapd.daemon.loop_lag.cause`: ``busy`` running code
    on it, ``waiting`` to run), None when the document does not say."""
    lp = s.get("loop")
    return cause(lp.get("last_stall_ms"), lp.get("last_stall_ran_ms")) if isinstance(lp, dict) else None


def recording_failing(rec: dict[str, Any] | None) -> bool:
    """Whether the recording fails to write now (or leaves messages out behind a slow disk). A
    document without ``writing`` (a daemon from before it) counts any failure so far."""
    if not isinstance(rec, dict):
        return False
    if "writing" in rec:
        return rec.get("writing") is False or rec.get("behind") is True
    return bool(rec.get("failures") or rec.get("dropped"))


def status_line(s: dict[str, Any]) -> str:
    """``FAULTS uwb port reopened 2 times | map v12; peers beta v9, gamma v4 (gone); global 3 maps 812x604``.

    Faults come first when there are any (a unit's status line is cut at the terminal's width).
    """
    parts = []
    src = s.get("source") or {}
    mine = f"map {label(src['version'])}" if src.get("version") else "no map yet"
    parts.append(mine + (" (source finished)" if src.get("finished") else ""))
    peers = s.get("peers") or {}
    if peers:
        shown = [
            f"{name} {label(p.get('version'))}" + ("" if p.get("present", True) else " (gone)")
            for name, p in list(peers.items())[:4]
            if isinstance(p, dict)
        ]
        more = f" +{len(peers) - 4}" if len(peers) > 4 else ""
        parts.append("peers " + ", ".join(shown) + more)
    else:
        parts.append("no peers yet")
    g = (s.get("fusion") or {}).get("global") or {}
    if g:
        n = (s.get("fusion") or {}).get("maps", 0)
        parts.append(f"global {n} map{'' if n == 1 else 's'} {g.get('width')}x{g.get('height')}")
    faults = [
        f"{name} {', '.join(words)}"
        for name, st in (s.get("links") or {}).items()
        if isinstance(st, dict) and (words := link_faults(st))
    ]
    if isinstance(src.get("stats"), dict) and (words := link_faults(src["stats"])):
        faults.insert(0, f"source {', '.join(words)}")  # a source on zenoh (ros2) waits as a link does
    if isinstance(skipped := src.get("skipped"), dict):
        faults.insert(0, f"own map not shared ({skipped.get('why')})")
    faults += [
        f"output.{name} {', '.join(words)}"
        for name, st in (s.get("outputs") or {}).items()
        if isinstance(st, dict) and (words := link_faults(st))
    ]
    faults += peer_faults(s)
    faults += state_faults(s)
    if recording_failing(s.get("recording")):
        faults.append("recording: messages not written")
    if (held := loop_held(s)) is not None:
        why = "code ran on it: a bug" if loop_cause(s) == "busy" else "overloaded, swapping or stopped?"
        faults.append(f"event loop held {held:.2f} s ({why})")
    if not (s.get("security") or {}).get("signed", True):
        faults.append("UNSIGNED fleet")
    line = ("FAULTS " + ", ".join(faults) + " | " if faults else "") + "; ".join(parts)
    return line if len(line) <= MAX_LINE else line[: MAX_LINE - 3] + "..."


def too_big_words(stats: dict[str, Any]) -> str | None:
    """A link's ``too_big_for`` in words (who, of its ``too_big_peers`` fault, and what to raise),
    for ``mapd status``; None when empty.

    Read from a status document (JSON from the daemon), so every field is checked, not trusted.
    """
    small = stats.get("too_big_for")
    if not isinstance(small, dict) or not small:
        return None
    peers = [
        f"{peer} takes {o.get('limit')} B, ours {o.get('size')} B (raise it on {peer} to at least "
        f"{o.get('size')})"
        for peer, o in small.items()
        if isinstance(o, dict)
    ]
    if not peers:
        return None
    total = stats.get("too_big_peers")
    if isinstance(total, int) and total > len(peers):
        peers.append(f"{total - len(peers)} more")
    return "maps too big for peers' limits.max_message_bytes: " + "; ".join(peers)
