"""What a swarm run measured: staleness per (holder, origin), convergence, channel use, bytes, losses.

**Staleness** of holder ``h``'s copy of origin ``o``'s map at time ``t``: 0 while ``h`` holds the
newest version ``o`` has made by ``t``; otherwise how long ``h`` has been behind, ``t`` minus the time
``o`` made the oldest version newer than the one ``h`` holds (with nothing held: ``t`` minus the time
of ``o``'s first version). So a holder that gets every version ``d`` seconds after it is made is
stale ``d`` seconds at most, and one that never hears ``o`` is as stale as ``o``'s map is old.
It is sampled every ``dt`` seconds over ``[0, duration]`` (while versions are made) for every ordered
pair, and p50, p95 and max are taken over all samples of all pairs (also in periods). With range
limits, ``p95 reach`` is the p95 over the pairs that were in range at least once (the rest can only
be served by relay), and ``never in range`` is the share of pairs that never were.

**Convergence**: after the last version any robot made, the time until every robot holds every other
robot's last version (``inf`` when the run ended first).

**Channel use**: the share of ``[0, duration]`` during which any frame was on the air (with range
limits: anywhere in the building), so it is at most 1; **offered** is the sum of all airtime over the
same span (over 1 means frames overlapped). **ack %** and **hello %** are those frames' share of
airtime; **bit/s per robot** is what each radio sent; **x coded** is radio bytes over the coded
envelopes' bytes (the protocol's overhead factor). Collisions and losses count (frame, receiver)
pairs: ``collided`` (another audible frame overlapped), ``deaf`` (the receiver was sending),
``lost`` (per-frame and per-wall loss).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from mapd.bench.swarm.radio import channel_use
from mapd.bench.swarm.sim import SwarmResult

#: ``(holder, origin, staleness samples over [0, t_end])`` for each pair, origin by origin.
StalenessRows = list[tuple[int, int, np.ndarray]]


def staleness_rows(
    made: list[list[float]], accepted: list[tuple[float, int, int, int]], t_end: float, dt: float = 1.0
) -> StalenessRows:
    """Each (holder, origin) pair's staleness samples (seconds) over ``[0, t_end]``, origin by origin."""
    n = len(made)
    ts = np.arange(0.0, t_end + 1e-9, dt)
    by_pair: dict[tuple[int, int], list[tuple[float, int]]] = {}
    for t, h, o, v in accepted:
        by_pair.setdefault((h, o), []).append((t, v))
    rows: StalenessRows = []
    for o in range(n):
        mt = np.asarray(made[o], dtype=np.float64)
        if mt.size == 0:
            continue
        newest = np.searchsorted(mt, ts, side="right")  # versions made by t (the newest's number)
        for h in range(n):
            if h == o:
                continue
            recs = by_pair.get((h, o), [])
            held = np.zeros(ts.shape, dtype=np.int64)
            if recs:
                rt = np.asarray([r[0] for r in recs])
                rv = np.maximum.accumulate(np.asarray([r[1] for r in recs], dtype=np.int64))
                k = np.searchsorted(rt, ts, side="right")
                held = np.where(k > 0, rv[np.maximum(k - 1, 0)], 0)
            behind = held < newest
            first_missing = np.minimum(held, mt.size - 1)  # index of version held + 1
            rows.append((h, o, np.where(behind, ts - mt[first_missing], 0.0)))
    return rows


def staleness_samples(
    made: list[list[float]], accepted: list[tuple[float, int, int, int]], t_end: float, dt: float = 1.0
) -> np.ndarray:
    """Staleness samples (seconds) of every (holder, origin) pair over ``[0, t_end]`` (one flat array)."""
    return _flat(staleness_rows(made, accepted, t_end, dt))


def _flat(rows: StalenessRows) -> np.ndarray:
    return np.concatenate([s for _, _, s in rows]) if rows else np.zeros(0)


#: Hop classes of :func:`staleness_by_hops`: how far apart holder and origin are at a sample.
HOP_CLASSES = ("1", "2", "3+", "none")


def staleness_by_hops(
    rows: StalenessRows, hops: list[tuple[float, np.ndarray]], dt: float = 1.0
) -> dict[str, dict[str, float]]:
    """Where the staleness lies: the samples (``rows``, a ``dt`` apart from 0 s) split by how many
    radio hops apart holder and origin were at the time (``hops``: each link update's time and hop
    counts, -1 for no path).

    Per class: ``samples`` (its share of all samples), ``mean_s``, and ``tail`` (its share of the
    samples at or above the p95), so a p95 set by pairs in direct range (the channel or the MAC) is
    told from one set by pairs that only a relay can serve."""
    if not hops or not rows:
        return {}
    times = np.asarray([t for t, _ in hops])
    stack = np.stack([h for _, h in hops])
    ts = dt * np.arange(rows[0][2].size)
    at = np.maximum(np.searchsorted(times, ts, side="right") - 1, 0)
    parts: dict[str, list[np.ndarray]] = {c: [] for c in HOP_CLASSES}
    for h, o, s in rows:
        hp = stack[at, h, o]
        for c, m in zip(HOP_CLASSES, (hp == 1, hp == 2, hp >= 3, hp < 0), strict=True):
            parts[c].append(s[m])
    flat = {c: np.concatenate(v) if v else np.zeros(0) for c, v in parts.items()}
    total = sum(a.size for a in flat.values())
    if not total:
        return {}
    p95 = float(np.percentile(np.concatenate(list(flat.values())), 95))
    tail = max(1, sum(int((a >= p95).sum()) for a in flat.values()))
    return {
        c: {
            "samples": a.size / total,
            "mean_s": float(a.mean()) if a.size else 0.0,
            "tail": int((a >= p95).sum()) / tail,
        }
        for c, a in flat.items()
    }


def staleness_trend(rows: StalenessRows, t_end: float, windows: int = 6) -> list[list[float]]:
    """``[[window start s, mean staleness s], ...]`` over ``windows`` equal windows of ``[0, t_end]``
    (``rows`` sampled once a second): flat once the channel keeps up, rising all run long when it
    does not."""
    if not rows:
        return []
    st = np.stack([s for _, _, s in rows])  # (pairs, samples), one a second
    edges = np.linspace(0.0, t_end, windows + 1)
    ts = np.arange(st.shape[1], dtype=np.float64)
    out = []
    for a, b in itertools.pairwise(edges):
        m = (ts >= a) & (ts < b)
        out.append([float(a), float(st[:, m].mean()) if m.any() else 0.0])
    return out


def convergence(made: list[list[float]], accepted: list[tuple[float, int, int, int]], n: int) -> float:
    """Seconds from the last version made to every robot holding every other robot's last version."""
    finals = [len(m) for m in made]
    last = max((m[-1] for m in made if m), default=0.0)
    got: dict[tuple[int, int], float] = {}
    for t, h, o, v in accepted:
        if v >= finals[o] and (h, o) not in got:
            got[(h, o)] = t
    need = [(h, o) for h in range(n) for o in range(n) if h != o and finals[o] > 0]
    if any(p not in got for p in need):
        return math.inf
    return max(0.0, max((got[p] for p in need), default=last) - last)


def summarize(res: SwarmResult) -> dict[str, Any]:
    """One row of the table (and of the JSON)."""
    cfg = res.config
    dur = cfg.duration
    rows = staleness_rows(res.made, res.accepted, dur)  # once: every figure below is made from them
    st = _flat(rows)
    p50, p95, mx = (float(np.percentile(st, q)) for q in (50, 95, 100)) if st.size else (0.0, 0.0, 0.0)
    reach = _flat([r for r in rows if res.ever_heard[r[0], r[1]]])
    reach_p95 = float(np.percentile(reach, 95)) if reach.size else math.nan
    off = ~np.eye(res.n, dtype=bool)
    r = res.radio
    c = r.counters
    airtime = max(c.airtime_s, 1e-12)
    bytes_tx = [rb.arq.counters.bytes_tx for rb in res.robots]
    coded = sum(rb.coded_bytes for rb in res.robots)
    pairs = c.delivered + c.collided + c.deaf + c.lost
    return {
        "robots": res.n,
        "codec": cfg.codec,
        "mac": cfg.mac,
        "range_m": cfg.range_m,
        "stale_p50_s": p50,
        "stale_p95_s": p95,
        "stale_max_s": mx,
        "stale_p95_periods": p95 / cfg.period,
        "stale_p95_reach_s": reach_p95,
        "never_in_range": float((~res.ever_heard & off).sum()) / max(1, int(off.sum())),
        "converge_s": convergence(res.made, res.accepted, res.n),
        "channel_use": channel_use(r.intervals, 0.0, dur),
        "offered": sum(min(e, dur) - s for s, e in r.intervals if s < dur) / dur,
        "ack_share": c.by_kind.get("ack", 0.0) / airtime,
        "hello_share": c.by_kind.get("hello", 0.0) / airtime,
        "bps_per_robot": 8.0 * float(np.mean(bytes_tx)) / max(res.end, 1e-9),
        "coded_bps_per_robot": 8.0 * coded / res.n / max(dur, 1e-9),
        "x_coded": sum(bytes_tx) / coded if coded else math.inf,
        "keyframes": sum(rb.keyframes for rb in res.robots),
        "deltas": sum(rb.deltas for rb in res.robots),
        "versions": sum(len(m) for m in res.made),
        "accepted": len(res.accepted),
        "frames": c.frames,
        "collided": c.collided,
        "deaf": c.deaf,
        "lost": c.lost,
        "collided_share": (c.collided + c.deaf) / pairs if pairs else 0.0,
        "kf_requests": sum(rb.kf_requests for rb in res.robots),
        "relayed": sum(rb.relayed for rb in res.robots),  # relays started (flood or summary)
        "summaries": sum(rb.summaries for rb in res.robots),
        # how much a robot learns of what its neighbours hold: one received per neighbour per
        # summary queued at best (docs/swarm.md, issue #22: at 16 robots in the building, about a twentieth)
        "summaries_rx": sum(rb.summaries_rx for rb in res.robots),
        # chunks sent, parity and resends among them
        "data_frames": sum(rb.arq.counters.data_tx for rb in res.robots),
        "parity_frames": sum(rb.arq.counters.parity_tx for rb in res.robots),
        "resends": sum(rb.arq.counters.resends for rb in res.robots),
        "superseded": sum(rb.arq.counters.superseded for rb in res.robots),
        "messages_delivered": sum(rb.arq.counters.messages_delivered for rb in res.robots),
        # where the staleness lies (JSON only): by hops between holder and origin, and over the run
        "stale_by_hops": staleness_by_hops(rows, res.hops),
        "stale_trend": staleness_trend(rows, dur),
        "hears_all": res.hears_all_share,
        "robot_hears_all": res.robot_hears_all_share,
        "degree": res.mean_degree,
        "sim_s": res.end,
        "wall_s": res.wall_s,
        "events": res.events,
    }
