"""What ``mapd status`` prints: a daemon's status document (:meth:`Daemon.snapshot`, as JSON over
its control socket) in lines an operator reads, with each fault on a ``FAULTS`` line of its own
where it belongs (the source, a peer, a link, the state directory, an output), in the words of the
log line that said it once. A pure function of the document, which comes from another process: every
field is checked, not trusted.
"""

from __future__ import annotations

import math
import time
from typing import Any


def _age(seconds: Any) -> str:
    if not isinstance(seconds, int | float):
        return "-"
    return f"{seconds:.0f}s" if seconds < 120 else f"{seconds / 60:.0f}m"


def _num(v: Any, spec: str = ".1f") -> str:
    if isinstance(v, float) and not math.isfinite(v):
        return "-"
    if not isinstance(v, int | float):
        return "-"
    text = format(v, spec)
    if text.startswith("-") and float(text) == 0.0:  # -0.04 ms printed "-0.0": nothing, with a sign
        text = ("+" if "+" in spec else "") + text[1:]
    return text


def render_status(s: dict[str, Any]) -> str:
    """A readable summary of one status document."""
    from mapd.daemon.headline import (
        DAMAGE_KEYS,
        LINK_FAULTS,
        damage_words,
        link_faults,
        loop_held,
        recording_failing,
        state_faults,
        too_big_words,
    )
    from mapd.daemon.versions import label

    out = []
    src = s.get("source", {})
    out.append(
        f"robot {s.get('robot')} (fleet {s.get('fleet')}), pid {s.get('pid')}, up {_age(s.get('uptime_s'))}"
    )
    sec = s.get("security", {})
    if sec.get("signed"):
        out.append(f"trust   signed; roster: {', '.join(sec.get('roster') or []) or '-'}")
    else:
        out.append("trust   UNSIGNED (fleet.allow_unsigned = true): anyone can write as any robot")
    rl = s.get("reload") or {}
    if rl.get("count"):
        at = rl.get("last_at")
        ago = _age(time.time() - at) if isinstance(at, int | float) else "-"
        out.append(
            f"reload  {rl['count']} ({rl.get('refused', 0)} refused); last {ago} ago: {rl.get('last')}"
        )
    size = src.get("size") or ["-", "-"]
    done = ", finished" if src.get("finished") else ""
    out.append(
        f"source  {src.get('name')}: map {label(src.get('version'))} ({size[0]} x {size[1]} cells{done})"
    )
    if isinstance(src.get("stats"), dict) and (faults := link_faults(src["stats"])):
        out.append("        FAULTS " + ", ".join(faults))
    if isinstance(skipped := src.get("skipped"), dict):
        out.append(
            f"        FAULTS own map not shared: its last {skipped.get('maps')} maps skipped ({skipped.get('why')})"
        )
    c = s.get("codec", {})
    out.append(
        f"codec   {c.get('name')}: last {label(c.get('last_version'))} {c.get('last_kind', '')} "
        f"{c.get('last_bytes', '-')} B, ratio {_num(c.get('last_ratio'))}:1, encode {_num(c.get('last_encode_ms'))} ms"
        f"; keyframes {c.get('keyframes', 0)}, deltas {c.get('deltas', 0)}"
        + (
            f", {c['reoffers']} offered again (robots come into range, or failed)"
            if c.get("reoffers")
            else ""
        )
        + "".join(f", {n} failed on {link}" for link, n in sorted((c.get("failed") or {}).items()) if n)
    )
    for name, o in (s.get("offers") or {}).items():
        air = {True: ", wholly on the air", False: ", still going out", None: ""}[o.get("on_air")]
        out.append(
            f"offer   {name}: {label(o.get('version'))} for {_age(o.get('age_s'))}{air}; "
            f"waiting for {', '.join(o.get('waiting') or []) or '-'}"
        )
    out.append("peers")
    peers = s.get("peers", {})
    # peers whose "acked our" is their radio's only: their daemon refuses our maps (uwb refused_by)
    links = s.get("links") or {}
    radio_only = {p for st in links.values() if isinstance(st, dict) for p in st.get("refused_by") or {}}
    # peers that announced a smaller limits.max_message_bytes than our maps (zenoh too_big_for)
    too_small = {
        p: o
        for st in links.values()
        if isinstance(st, dict) and isinstance(st.get("too_big_for"), dict)
        for p, o in st["too_big_for"].items()
        if isinstance(o, dict)
    }
    if not peers:
        out.append("  (none yet)")
    for name, p in peers.items():
        refused = p.get("refused") if isinstance(p.get("refused"), dict) else None
        # a robot known only by maps refused (off the roster, say): heard, not a peer "up"
        state = "heard" if refused and "present" not in p else "up" if p.get("present", True) else "gone"
        if p.get("restored"):
            state += " (map from state dir)"
        via = p.get("link", "-")
        if isinstance(relay := p.get("relayed_by"), str):
            via = f"{via} (relayed by {relay})"
        # 0: no ack known (none yet, none relayed back, or forgotten when it asked for a whole map
        # or restarted); "v0" read as an ack of a version 0 it never had
        acked = p.get("acked_our_version") or 0
        out.append(
            f"  {name:<12} {label(p.get('version')):<6} age {_age(p.get('age_s')):>5}  {p.get('bytes', 0):>9} B  "
            f"{p.get('updates', 0):>4} updates  via {via}  {state}  acked our {label(acked) if acked else 'none known'}"
        )
        # What disagrees between its config and ours, on lines of its own: with the fix, in the
        # words of the log line that said it once.
        if refused:
            out.append(
                f"  {'':<12} FAULTS {refused.get('maps', '?')} maps refused for {_age(refused.get('for_s'))}, "
                f"last {_age(refused.get('last_s'))} ago: {refused.get('fix') or refused.get('why')}"
            )
        if p.get("takes_ours") is False:
            out.append(
                f"  {'':<12} FAULTS takes none of this robot's maps for {_age(p.get('unacked_s'))} while its "
                f"own come: on {name}, is this robot's key in its [fleet.roster] (the current one), are "
                f"its limits as large as this robot's maps?"
            )
        if name in too_small:
            o = too_small[name]
            out.append(
                f"  {'':<12} FAULTS takes messages up to {o.get('limit')} B, this robot's maps are "
                f"{o.get('size')} B: raise limits.max_message_bytes on {name} to at least {o.get('size')}"
            )
        if name in radio_only:
            out.append(
                f"  {'':<12} FAULTS acks our maps at the radio (uwb) but its daemon refuses them: its "
                f"mapd status says why"
            )
        if isinstance(p.get("heard_as"), str):
            out.append(
                f"  {'':<12} FAULTS its link knows it as '{p['heard_as']}': the robots' [transports.uwb] "
                f"nodes lists differ; make them the same on every robot"
            )
    out.append("links")
    for name, st in s.get("links", {}).items():
        head = ("rate_bps", "goodput_bps", "bytes_tx", "bytes_rx", "resends", "parity_tx", "recovered")
        # A serial link's damaged frames as one total, whatever caught them: a wrong baud raises
        # cobs_errors and oversize, a keyed link's damage lands in bad_signature; only the first 8
        # other counters fit, and they never reached those. A zenoh link's bad_signature as it is.
        damage = damage_words(st)
        hidden = set(DAMAGE_KEYS) if damage is not None else set()
        keys = (*head, "crc_errors", "bad_signature", "rtt_ms")
        parts = [f"{k}={_num(st[k], '.0f')}" for k in keys if k in st and k not in hidden]
        if damage is not None:
            parts.insert(len([k for k in head if k in st]), damage)
        faults = link_faults(st)
        relay = _relay_line(st)
        # Of the rest, what says a link struggles first (only 8 fit): in dict order, counters such
        # as completes_tx=0 took the places and timeouts, failed messages and the rate were cut.
        first = ("link_rate_bps", "timeouts", "messages_failed", "relays_failed", "in_flight", "peers_up")
        ordered = sorted(st.items(), key=lambda kv: first.index(kv[0]) if kv[0] in first else len(first))
        others = [
            f"{k}={v}"
            for k, v in ordered
            if k not in keys
            and k not in hidden
            and k not in LINK_FAULTS
            and not (relay and k.startswith("relay"))  # (on the relay's own line)
            and isinstance(v, int | float)
            and not isinstance(v, bool)
        ]
        out.append(f"  {name:<6} " + " ".join(parts + others[:8]))
        if faults:
            # Said on a line of its own, whatever the link's other figures: what needs a look.
            out.append(f"  {'':<6} FAULTS " + ", ".join(faults))
        if relay:
            out.append(f"  {'':<6} {relay}")
        if (clock := _radio_clock_line(st.get("radio_clock"))) is not None:
            out.append(f"  {'':<6} {clock}")
        if isinstance(big := st.get("oversize_from"), dict) and big:
            out.append(
                f"  {'':<6} maps over limits.max_message_bytes from "
                + ", ".join(f"{robot} ({size} B)" for robot, size in big.items())
            )
        if (small := too_big_words(st)) is not None:  # who, of the too_big_peers fault above
            out.append(f"  {'':<6} {small}")
        if isinstance(fleets := st.get("other_fleets"), dict) and fleets:
            # No fault: fleets may share a network on purpose. But the one thing that says why a
            # robot with another robot.fleet is never seen.
            out.append(
                f"  {'':<6} other fleets on this network: "
                + ", ".join(f"{fleet} ({', '.join(map(str, robots))})" for fleet, robots in fleets.items())
            )
        if isinstance(older := st.get("older_mapd"), dict) and older:
            # No fault: a fleet upgraded one robot at a time; what those robots get meanwhile.
            out.append(
                f"  {'':<6} older mapd (not sent what it lacks): "
                + ", ".join(f"{robot} (lacks {lacks})" for robot, lacks in older.items())
            )
        if isinstance(own := st.get("own_clock"), list) and own:
            # No fault either (a rolling upgrade to radio time), but turns on two clocks may overlap.
            out.append(
                f"  {'':<6} turns on their own clock, not this radio clock: {', '.join(map(str, own))} "
                "(set one clock on every robot)"
            )
        if isinstance(refusing := st.get("refused_by"), dict) and refusing:
            out.append(
                f"  {'':<6} daemons refusing our maps their radios ack: "
                + ", ".join(
                    f"{peer} (acked {label(r.get('acked'))}, holds {label(r.get('holds')) if r.get('holds') else 'none'})"
                    for peer, r in refusing.items()
                    if isinstance(r, dict)
                )
            )
    f = s.get("fusion", {})
    g = f.get("global") or {}
    out.append(
        f"fusion  {f.get('maps', 0)} maps merged, {f.get('merges', 0)} merges, global "
        f"{g.get('width', '-')} x {g.get('height', '-')} cells, last merge {_num(f.get('last_merge_s'), '.2f')} s"
    )
    for robot, t in (f.get("robots") or {}).items():
        if isinstance(t, dict):
            acc = "accepted" if t.get("accepted") else f"not accepted ({t.get('reason') or '?'})"
            out.append(
                f"  {robot:<12} {label(t.get('version'))}  x {_num(t.get('x'), '.2f')} m  y {_num(t.get('y'), '.2f')} m  "
                f"yaw {_num(t.get('yaw'), '.3f')} rad  conf {_num(t.get('confidence'), '.2f')}  {t.get('source', '')}  {acc}"
            )
    poses = (s.get("poses") or {}).get("robots") or {}
    if poses:
        out.append(
            "poses   (x m, y m, yaw rad; in each robot's map frame, and in the fleet frame once placed)"
        )
    for robot, p in poses.items():
        where = " ".join(_num(v, ".2f") for v in p.get("map", []))
        fleet = p.get("fleet")
        in_fleet = " ".join(_num(v, ".2f") for v in fleet) if fleet else "not placed"
        # (a robot its link no longer hears is where it was, not where it is; the age alone does
        # not say it: AMCL publishes only when the robot moves, a parked robot's pose is old)
        peer = (s.get("peers") or {}).get(robot)
        gone = "  (not heard now)" if isinstance(peer, dict) and peer.get("present") is False else ""
        out.append(f"  {robot:<12} map {where:<20} fleet {in_fleet:<20} age {_age(p.get('age_s'))}{gone}")
    for name, st in (s.get("outputs") or {}).items():
        if isinstance(st, dict) and (faults := link_faults(st)):
            out.append(f"output  {name}: FAULTS " + ", ".join(faults))
    if faults := state_faults(s):
        st = s["state"]
        failing = [x for x in (st, st.get("global_map") or {}) if x.get("writing") is False]
        since = max((x.get("failing_s") or 0 for x in failing), default=0)
        out.append(
            f"state   FAULTS {'; '.join(faults)}, for {_age(since)} ({st.get('dir')}): "
            f"{next((x.get('error') for x in failing if x.get('error')), '-')}"
        )
    rec = s.get("recording")
    if rec and (rec.get("failures") or rec.get("dropped")):
        counts = (
            f"{rec.get('failures', 0)} messages not written (disk full?), {rec.get('dropped', 0)} left "
            f"out behind a slow disk ({rec.get('queued_bytes', 0) >> 20} MiB waiting)"
        )
        # a fault while it lasts; afterwards the totals, on a line of their own but not a fault
        out.append(f"record  FAULTS {counts}" if recording_failing(rec) else f"record  so far: {counts}")
    if isinstance(lp := s.get("loop"), dict):
        out.append(_loop_line(lp, loop_held(s)))
    bad = {k: v for k, v in s.get("counters", {}).items() if v}
    if bad:
        out.append("counters " + " ".join(f"{k}={v}" for k, v in bad.items()))
    return "\n".join(out)


def _loop_line(lp: dict[str, Any], held: float | None) -> str:
    """How late the event loop ran (:mod:`mapd.daemon.loop_lag`); a fault while a hold of a second
    or more is recent (``held``: :func:`mapd.daemon.headline.loop_held`), with its cause."""
    from mapd.daemon.headline import loop_cause

    line = (
        f"loop    late by at most {_num(lp.get('lag_ms_recent_max'), '.0f')} ms in the last "
        f"{_age(lp.get('recent_s'))} (p99 {_num(lp.get('lag_ms_recent_p99'), '.0f')} ms), "
        f"{_num(lp.get('lag_ms_max'), '.0f')} ms since start"
    )
    stalls, last, ago = lp.get("stalls"), lp.get("last_stall_ms"), lp.get("last_stall_ago_s")
    if not isinstance(stalls, int) or not stalls or not isinstance(last, int | float):
        return line + f"; no stalls of {_num(lp.get('stall_ms'), '.0f')} ms or more"
    n = f"{stalls} stall{'' if stalls == 1 else 's'}"
    why, ran_ms = loop_cause({"loop": lp}), lp.get("last_stall_ran_ms")
    ran = ran_ms / 1000 if why is not None and isinstance(ran_ms, int | float) else 0.0
    if held is not None:
        head = f"loop    FAULTS the event loop was held {held:.2f} s {_age(ago)} ago ({n} in all)"
        if why == "busy":
            return (
                f"{head}, running code on it for {ran:.2f} s: work that belongs in a worker "
                f"thread (a bug of mapd or of a plugin: report it with the daemon's log)"
            )
        if why == "waiting":
            return (
                f"{head}, waiting (it ran {ran:.2f} s of it): radio turns and timers waited; is the "
                f"computer overloaded or swapping, was it stopped, or did a call on the loop block?"
            )
        return (
            f"{head}: radio turns and timers waited; is the computer overloaded, swapping, or was it stopped?"
        )
    how = {"busy": ", running code on the loop", "waiting": ", waiting"}.get(why or "", "")
    return (
        line
        + f"; {n} of {_num(lp.get('stall_ms'), '.0f')} ms or more, the last {last / 1000:.2f} s{how}, "
        + f"{_age(ago)} ago"
    )


def _radio_clock_line(rc: Any) -> str | None:
    """The clock a uwb link counts its TDMA turns on (``radio_clock``, from
    :mod:`transports.uwb.radio_time`), in words; None for a link without radio time."""
    if not isinstance(rc, dict):
        return None
    sent = f"{_num(rc.get('time_beacons_tx'), '.0f')} TIME frames sent"
    if rc.get("role") == "source":
        return (
            f"clock   turns on the wall clock, which a time service keeps; leads robots without one ({sent})"
        )
    if rc.get("role") == "leads":
        return (
            f"clock   leads the fleet's TDMA turns: no robot heard has a time service or a lower link id "
            f"(its correction {_num(rc.get('correction_ms'), '.1f')} ms; {sent})"
        )
    hops = rc.get("hops")
    measured = "" if rc.get("delay_measured") else " (its airtime: not measured yet)"
    whose = (
        "a time service's clock" if rc.get("root_is_source") else "no time service: the lowest link id leads"
    )
    return (
        f"clock   turns on {rc.get('root')}'s clock over the radio ({whose}), {hops} hop{'s' if hops != 1 else ''} "
        f"via {rc.get('parent')}: {_num(rc.get('correction_ms'), '+.1f')} ms on the wall clock, "
        f"{_num(rc.get('rate_ppm'), '+.1f')} ppm, path delay {_num(rc.get('delay_ms'), '.1f')} ms{measured}, "
        f"last TIME {_num(rc.get('synced_ago_s'), '.0f')} s ago ({sent})"
    )


def _relay_line(st: dict[str, Any]) -> str | None:
    """What a uwb link's multi-hop relay did (``relays_tx`` and the rest, from
    :mod:`transports.uwb.relaying`), in words; None for a link without one. The eight figures the
    links line has room for never reached these, so a relaying robot's status did not show them."""
    tx = st.get("relays_tx")
    if not isinstance(tx, int) or isinstance(tx, bool):
        return None

    def n(key: str) -> str:
        return _num(st.get(key), ".0f")

    bad = f" ({n('relay_bad_summaries')} malformed)" if st.get("relay_bad_summaries") else ""
    return (
        f"relay   forwarded {tx} maps of other robots ({n('relays_failed')} given up, "
        f"{n('relays_overheard')} overheard from neighbours), {n('relay_keyframes_asked')} whole maps "
        f"asked for on a neighbour's behalf; summaries {n('relay_summaries_tx')} sent, "
        f"{n('relay_summaries_rx')} heard{bad}"
    )
