"""The live view's state and the messages it sends: sans-I/O (no asyncio, no clock; ``now`` comes in).

Two models, because they live on two threads and must never wait for each other:

* :class:`MapModel`, fed on the daemon's output thread: the global map as tiles (only changed tiles
  are encoded and sent), each robot's placed map outline, its pose and trail in the fleet frame
  (kept in the robot's own map frame and placed when sent, so a trail follows a re-placed robot).
* :class:`StatusModel`, fed on the event loop with the daemon's status dict (what ``mapd status``
  shows): link rates against the radio budget (from byte counters between two snapshots), RTT,
  resends, last heard, and per robot its versions, keyframes/deltas, bytes and fusion confidence.

Both return :class:`~mapd.view.queue.Message` frames, encoded once for all viewers.

The ``map`` message (format :data:`MAP_FORMAT`; the page ships with the server and reloads itself
on a format it does not know)::

    {"format": 2, "seq": n, "version": v, "stamp": s, "versions": {...},
     "geometry": {"width", "height", "resolution", "origin": [x, y], "tile": 128, "lattice": [c, r]},
     "full": bool, "tiles": [[tx, ty, "<base64 palette PNG>"], ...]}

``tiles`` are on the fleet frame's tile lattice (:mod:`mapd.view.tiles`). ``full``: the viewer starts
from a blank canvas (all unknown) of the new geometry. Otherwise the message follows the one of
``seq - 1`` (map messages reach a viewer in order, or it is resynced with a full one): with the same
geometry, its tiles are drawn over the canvas; with another one (the map grew or moved by whole cells
on the same lattice), the viewer first makes a canvas of the new size and copies the old one into it
at ``old lattice - new lattice`` pixels, then draws the tiles. The tiles sent are those with a
changed cell and those new or whose extent changed (edge tiles): every cell of the new canvas is
then as the map says, exactly as if the whole map had been sent. A change of resolution, or an
origin moved by a fraction of a cell, goes out ``full``.
"""

from __future__ import annotations

import base64
import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapd.fusion.transforms import compose
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.outputs.base import GlobalUpdate
from mapd.view.queue import Message, sse
from mapd.view.tiles import Geometry, all_tiles, changed_tiles, class_image, encode_tile

#: The ``map`` message's format: bumped when the page must draw its tiles another way (2: tiles on
#: the fleet frame's lattice, and grown maps sent as deltas).
MAP_FORMAT = 2
#: Robot colours (the demo report's, as CSS): robots get them in the order they are first seen.
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")
#: Trail points kept per robot (older ones fall off: memory stays bounded however long it runs).
TRAIL = 300
#: Link rates are averaged over about this long (seconds).
RATE_WINDOW_S = 10.0
#: A trail point is added once the robot moved this far (m), so a robot standing still adds none.
TRAIL_STEP_M = 0.05


@dataclass(frozen=True)
class RobotMap:
    """A robot's own map, as far as the view needs it: its size and where cell (0, 0) lies."""

    width: int
    height: int
    resolution: float
    origin: Pose2D

    @staticmethod
    def of(grid: OccupancyGrid) -> RobotMap:
        return RobotMap(grid.width, grid.height, grid.resolution, grid.origin)

    def outline(self, frame: Pose2D) -> list[list[float]]:
        """The map's four corners in the fleet frame, given its map frame's pose there."""
        w, h = self.width * self.resolution, self.height * self.resolution
        corners = [Pose2D(0, 0, 0), Pose2D(w, 0, 0), Pose2D(w, h, 0), Pose2D(0, h, 0)]
        out = []
        for c in corners:
            p = compose(frame, compose(self.origin, c))
            out.append([round(p.x, 3), round(p.y, 3)])
        return out


def _pose(p: Pose2D) -> list[float]:
    return [round(p.x, 3), round(p.y, 3), round(p.yaw, 4)]


def _placed(frame: Pose2D, points: Iterable[tuple[float, float]]) -> list[list[float]]:
    """Points of a robot's map frame in the fleet frame, given the map frame's pose there."""
    c, s = math.cos(frame.yaw), math.sin(frame.yaw)  # compose() per point, without a Pose2D each
    return [[round(frame.x + c * x - s * y, 3), round(frame.y + s * x + c * y, 3)] for x, y in points]


class MapModel:
    """The global map's tiles and the robots' placements, poses and trails (one thread only)."""

    def __init__(self, trail: int = TRAIL) -> None:
        self.seq = 0  # map messages made; a viewer's map is current when it has the latest seq
        self._image: np.ndarray | None = None
        self._geometry: Geometry | None = None
        self._tiles: dict[tuple[int, int], str] = {}  # base64 PNG per tile: the full state
        self._head: dict[str, Any] = {}
        self._full: Message | None = None
        self._colours: dict[str, str] = {}
        self._frames: dict[str, Pose2D] = {}
        self._maps: dict[str, RobotMap] = {}
        self._poses: dict[str, StampedPose] = {}
        #: Per robot, the points it passed, in its own map frame: fusion may place the map anew at
        #: any time, and the trail must move with it (placed in the fleet frame when sent).
        self._trails: dict[str, deque[tuple[float, float]]] = {}
        self._trail_len = trail
        #: Tiles encoded, in all (a measure of the work the diffs save).
        self.tiles_encoded = 0

    # -- the global map ----------------------------------------------------------------------
    def global_map(self, update: GlobalUpdate) -> Message:
        """A new global map: the ``map`` message with only the tiles that changed or are new.

        A map that grew or moved by whole cells is a delta too (its tiles are on the fleet frame's
        lattice); only a change of resolution or a fractional move sends every tile.
        """
        grid = update.grid
        image = class_image(grid)
        geometry = Geometry.of(grid)
        prev = self._geometry
        full = prev is None or self._image is None or not geometry.lines_up_with(prev)
        tiles = changed_tiles(None if full else self._image, image, geometry, prev)
        if full:
            self._tiles.clear()
        elif geometry != prev:
            # the full state keeps the tiles that did not change (same lattice place, same bytes)
            # and loses those now off the map (it shrank on a side)
            keep = set(all_tiles(geometry))
            for key in self._tiles.keys() - keep:
                del self._tiles[key]
        encoded = []
        for tx, ty in tiles:
            b64 = base64.b64encode(encode_tile(image, geometry, tx, ty)).decode("ascii")
            self._tiles[(tx, ty)] = b64
            encoded.append([tx, ty, b64])
        self.tiles_encoded += len(tiles)
        self._image, self._geometry = image, geometry
        self.seq += 1
        self._head = {
            "format": MAP_FORMAT,
            "seq": self.seq,
            "version": grid.version,
            "stamp": round(update.stamp, 3),
            "versions": dict(update.versions),
            "geometry": geometry.as_dict(),
        }
        self._full = None  # built when a viewer needs it
        for robot in self._frames.keys() - update.frames.keys():
            # No longer placed: its pose and trail are in no frame now; a placement that comes back
            # may put its map elsewhere (a new incarnation), so they start afresh then.
            self._trails.pop(robot, None)
            self._poses.pop(robot, None)
        self._frames = dict(update.frames)
        if update.poses:
            self._note_poses(update.poses)
        return sse("map", {**self._head, "full": full, "tiles": encoded}, self.seq)

    def full_map(self) -> Message | None:
        """The whole current map as one ``map`` message (for a new or resyncing viewer)."""
        if self._geometry is None:
            return None
        if self._full is None:
            tiles = [[tx, ty, b64] for (tx, ty), b64 in sorted(self._tiles.items())]
            self._full = sse("map", {**self._head, "full": True, "tiles": tiles}, self.seq)
        return self._full

    # -- robots ------------------------------------------------------------------------------
    def robot_maps(self, maps: dict[str, RobotMap]) -> None:
        """The size and origin of each robot's map (for its outline in the fleet frame)."""
        self._maps.update(maps)

    def poses(self, poses: dict[str, StampedPose], frames: dict[str, Pose2D]) -> Message:
        """New robot poses (each in its own map frame) and the placements to put them in the fleet frame."""
        self._frames.update(frames)
        self._note_poses(poses)
        return self.robots()

    def _note_poses(self, poses: dict[str, StampedPose]) -> None:
        for robot, sp in poses.items():
            if robot not in self._frames:
                continue  # not placed: in no frame to draw it in (its first pose once placed starts it)
            held = self._poses.get(robot)
            if held is not None and sp.stamp < held.stamp:
                continue  # a global map may carry a pose older than one already shown
            self._poses[robot] = sp
            # In the robot's own map frame (a rigid placement keeps distances: the step is the same).
            p = (sp.pose.x, sp.pose.y)
            trail = self._trails.setdefault(robot, deque(maxlen=self._trail_len))
            if not trail or math.dist(trail[-1], p) >= TRAIL_STEP_M:
                trail.append(p)

    def colour(self, robot: str) -> str:
        """This robot's colour in the view (sticky: the order robots were first seen)."""
        if robot not in self._colours:
            self._colours[robot] = COLOURS[len(self._colours) % len(COLOURS)]
        return self._colours[robot]

    def robots(self) -> Message:
        """The ``robots`` message: per robot its colour, placement, outline, pose and trail."""
        out: dict[str, Any] = {}
        for robot in sorted(set(self._frames) | set(self._maps) | set(self._poses)):
            frame = self._frames.get(robot)
            rmap = self._maps.get(robot)
            sp = self._poses.get(robot)
            pose = trail = None
            if frame is not None:
                if sp is not None:
                    pose = _pose(compose(frame, sp.pose))
                trail = _placed(frame, self._trails.get(robot, ()))
            out[robot] = {
                "colour": self.colour(robot),
                "frame": None if frame is None else _pose(frame),
                "outline": None if frame is None or rmap is None else rmap.outline(frame),
                "pose": pose,
                "pose_stamp": None if sp is None or frame is None else round(sp.stamp, 3),
                "trail": trail or [],
            }
        return sse("robots", {"robots": out})


# ---------------------------------------------------------------------------------- status


def _label(version: Any) -> str:
    """``v<number>`` as ``mapd status`` shows a version (the incarnation, the high 32 bits, left out)."""
    if not isinstance(version, int) or isinstance(version, bool) or version < 0:
        return "-"
    return f"v{version & 0xFFFFFFFF}"


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) else None


class StatusModel:
    """Turns the daemon's status dict into the ``status`` message (one thread only: the loop)."""

    def __init__(self, window_s: float = RATE_WINDOW_S) -> None:
        self.window_s = window_s
        # link -> (now, bytes_tx, bytes_rx) samples of the last window_s: a rate over a few
        # seconds, since one map update every few seconds makes a one-second rate jump 0 <-> peak
        self._samples: dict[str, deque[tuple[float, float, float]]] = {}

    def message(self, snap: dict[str, Any], now: float) -> Message:
        """The ``status`` message for a snapshot taken at ``now`` (seconds, any monotonic clock)."""
        peers: dict[str, Any] = snap.get("peers") or {}
        links = []
        for name, st in sorted((snap.get("links") or {}).items()):
            if not isinstance(st, dict):
                continue
            tx, rx = _num(st.get("bytes_tx")) or 0.0, _num(st.get("bytes_rx")) or 0.0
            samples = self._samples.setdefault(name, deque(maxlen=256))
            while samples and now - samples[0][0] > self.window_s:
                samples.popleft()
            prev = samples[0] if samples else None
            samples.append((now, tx, rx))
            tx_bps = rx_bps = None
            if prev is not None and now > prev[0]:
                tx_bps = round(8 * max(0.0, tx - prev[1]) / (now - prev[0]), 1)
                rx_bps = round(8 * max(0.0, rx - prev[2]) / (now - prev[0]), 1)
            budget = _num(st.get("link_rate_bps"))
            heard = [
                _num(p.get("age_s")) for p in peers.values() if isinstance(p, dict) and p.get("link") == name
            ]
            ages = [a for a in heard if a is not None]
            links.append(
                {
                    "name": name,
                    "tx_bps": tx_bps,
                    "rx_bps": rx_bps,
                    "budget_bps": budget,
                    "use": None if tx_bps is None or not budget else round(tx_bps / budget, 4),
                    "rtt_ms": _num(st.get("rtt_ms")),
                    "resends": _num(st.get("resends")),
                    "timeouts": _num(st.get("timeouts")),
                    "bytes_tx": tx,
                    "bytes_rx": rx,
                    "peers": st.get("peers") if isinstance(st.get("peers"), list) else [],
                    "last_heard_s": min(ages) if ages else None,
                }
            )
        fusion = snap.get("fusion") or {}
        placed: dict[str, Any] = fusion.get("robots") or {}
        me = str(snap.get("robot", ""))
        codec = snap.get("codec") or {}
        robots: dict[str, Any] = {}
        for robot in sorted(set(peers) | set(placed) | ({me} if me else set())):
            p = placed.get(robot) or {}
            entry: dict[str, Any] = {
                "accepted": bool(p.get("accepted")),
                "confidence": _num(p.get("confidence")),
                "agreement": _num(p.get("agreement")),
                "source": p.get("source"),
                "reason": p.get("reason") or "",
            }
            if robot == me:
                src = snap.get("source") or {}
                entry.update(
                    own=True,
                    version=src.get("version"),
                    size=src.get("size"),
                    keyframes=codec.get("keyframes", 0),
                    deltas=codec.get("deltas", 0),
                    bytes=codec.get("last_bytes"),
                )
            else:
                peer = peers.get(robot) or {}
                entry.update(
                    own=False,
                    version=peer.get("version"),
                    updates=peer.get("updates", 0),
                    bytes=peer.get("bytes", 0),
                    last_kind=peer.get("last_kind"),
                    age_s=_num(peer.get("age_s")),
                    present=peer.get("present"),
                    link=peer.get("link"),
                )
            entry["label"] = _label(entry.get("version"))
            # how old its last pose is (this daemon's clock against the stamp): the page fades a
            # robot last heard long ago, which it drew as if it were there now
            pose = (((snap.get("poses") or {}).get("robots") or {}).get(robot)) or {}
            entry["pose_age_s"] = _num(pose.get("age_s")) if isinstance(pose, dict) else None
            robots[robot] = entry
        g = fusion.get("global") or {}
        return sse(
            "status",
            {
                "robot": me,
                "fleet": snap.get("fleet"),
                "uptime_s": snap.get("uptime_s"),
                "signed": (snap.get("security") or {}).get("signed"),
                "links": links,
                "robots": robots,
                "global": {
                    "width": g.get("width"),
                    "height": g.get("height"),
                    "merges": fusion.get("merges"),
                },
            },
        )
