"""Where the daemon's results go: outputs, the MCAP recording and ``fused.csv``, all off the event loop.

:class:`Sinks` is called on the loop (:meth:`Sinks.global_map` by the fusion worker's callback,
:meth:`Sinks.robot_map` for every own or received map, :meth:`Sinks.links` on a timer) and hands
the work to two threads: one for the outputs (latest wins: a slow output skips maps, never queues
them) and one for files (the recording and the CSV, in order). Nothing that fails there stops the
daemon: it logs one line.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from mapd.daemon.coding import CsvLog
from mapd.files.outage import WriteOutage
from mapd.fusion.placement import Placement
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.outputs.base import GlobalUpdate, Output, PoseUpdate
from mapd.record.writer import Recorder
from mapd.ros2 import rmw
from mapd.ros2.diagnostics import OK, WARN, Diagnostic, flat_values
from mapd.ros2.tf import Ros2Names, robot_frame, tf_static

log = logging.getLogger("mapd.daemon")
#: The most the file thread may have waiting, in bytes of the maps it holds: a disk that is slow
#: rather than full (an SD card stalling, a network share) held every map the fleet made meanwhile.
MAX_QUEUED_BYTES = 256 << 20
#: What a message without a map is counted as (a pose, the links' counters, CSV rows).
_SMALL = 4096


def placed_frames(placements: dict[str, Placement]) -> dict[str, Pose2D]:
    """Each robot's map frame in the fleet frame, for the placements fusion accepted."""
    return {r: p.transform for r, p in placements.items() if p.accepted and p.transform is not None}


def link_diagnostics(links: dict[str, Any], robot: str) -> list[Diagnostic]:
    """Each link's counters (``{transport: stats}``) as a ``DiagnosticStatus``: its faults in
    ``mapd status``'s words (:func:`~mapd.daemon.headline.link_faults`) set level and message."""
    from mapd.daemon.headline import link_faults

    out = []
    for name, st in sorted(links.items()):
        faults = link_faults(st)
        out.append(
            Diagnostic(
                name=f"mapd: {name} link",
                level=WARN if faults else OK,
                message="; ".join(faults) if faults else "ok",
                hardware_id=robot,
                values=tuple(flat_values(st)),
            )
        )
    return out


class Sinks:
    """The outputs, the recording and ``fused.csv`` of one daemon."""

    def __init__(self, outputs: list[Output], recorder: Recorder | None, fused_log: CsvLog) -> None:
        self.outputs = outputs
        self.recorder = recorder
        self.fused_log = fused_log
        self._files = ThreadPoolExecutor(1, thread_name_prefix="mapd-files")
        self._out_pool = ThreadPoolExecutor(1, thread_name_prefix="mapd-outputs")
        self._out_next: GlobalUpdate | None = None
        self._pose_next: PoseUpdate | None = None
        #: Robot -> its newest map (and when taken) not yet handed to the outputs (latest wins; at
        #: most one per robot the daemon holds, which the roster bounds).
        self._robot_next: dict[str, tuple[OccupancyGrid, float]] = {}
        #: Robots whose map topic is no ROS 2 name (said once; not recorded): the roster bounds it.
        self._unnamed: set[str] = set()
        self._out_lock = threading.Lock()
        #: Messages the recorder could not write (a full disk): said once until it writes again.
        self.record_failures = 0
        self._record_outage = WriteOutage(log)
        #: Messages not recorded because the file thread was :data:`MAX_QUEUED_BYTES` behind.
        self.record_dropped = 0
        self._queued = 0  # bytes the file thread holds (changed on the loop and in that thread)
        self._queued_lock = threading.Lock()
        self._behind = WriteOutage(log)
        #: The latest known robot poses, which every GlobalUpdate carries too.
        self.poses_now: dict[str, StampedPose] = {}
        #: The latest /tf_static recorded (parent, child, pose), and every robot the recording ever
        #: placed (in this run, or in the one before: kept beside the recording's files).
        self._recorded_tf: list[tuple[str, str, Pose2D]] = []
        self._recorded_placed: set[str] = set(recorder.placed_before) if recorder is not None else set()
        #: Called on the loop with every robot map the daemon holds (the live view notes its size).
        self.map_watchers: list[Callable[[OccupancyGrid], None]] = []

    # ------------------------------------------------------------------ on the loop
    def global_map(
        self, grid: OccupancyGrid, placements: dict[str, Placement], robots: dict[str, Any]
    ) -> None:
        """A new global map, the placements it was merged with, and the fusion worker's status per robot."""
        wall = time.time()
        rows = [
            {"time": round(wall, 3), "robot": robot, "version": info["version"]}
            for robot, info in robots.items()
            if isinstance(info, dict) and info.get("accepted") and info.get("version")
        ]
        if rows:  # which version of each robot the global map holds (for latency benches)
            self._files.submit(self.fused_log.write, rows)
        frames = placed_frames(placements)
        if self.outputs:
            versions = {
                r: int(i["version"]) for r, i in robots.items() if isinstance(i, dict) and i.get("version")
            }
            update = GlobalUpdate(
                grid=grid, frames=frames, stamp=wall, versions=versions, poses=self.poses_now
            )
            self._to_outputs(update)
        if self.recorder is not None:
            names = self._names()
            self._record(self.recorder.grid, names.map_topic, grid, names.frames.frame, wall)
            # A robot no longer placed moves under unplaced_frame, as on the ros2 output: tf2 keeps
            # a static transform for as long as it runs, so one only left out of the next message
            # stayed placed when the recording was played.
            stamped, _, placed = tf_static(names.frames, frames, self._recorded_placed, wall)
            grown, self._recorded_placed = placed != self._recorded_placed, placed
            items = [(parent, child, pose) for parent, child, pose, _ in stamped]
            if items != self._recorded_tf:  # latched: written again only when a placement changes
                self._recorded_tf = items
                self._record(self.recorder.tf_static, items, wall, sorted(placed) if grown else None)

    def robot_map(self, grid: OccupancyGrid) -> None:
        """A robot's map as this daemon now holds it (its own, or one received)."""
        for watch in self.map_watchers:
            watch(grid)
        wall = time.time()
        if self.outputs:
            self._to_outputs(robot_map=(grid, wall))
        if self.recorder is not None and grid.robot not in self._unnamed:
            names = self._names()
            topic = robot_frame(names.robot_map_topic, grid.robot)
            try:  # robot names may hold '-' or begin with a digit; a topic may not (rcl)
                rmw.check_topic_name(topic)
            except ValueError as exc:  # ros2 bag play could not make its publisher: left out, as live
                self._unnamed.add(grid.robot)
                log.warning("record: robot %s: %s; its map is not recorded", grid.robot, exc)
                return
            frame = robot_frame(names.frames.robot_map_frame, grid.robot)
            self._record(self.recorder.grid, topic, grid, frame, wall)

    def poses(self, poses: dict[str, StampedPose], frames: dict[str, Pose2D]) -> None:
        """New robot poses (each ``base_link`` in its robot's map frame) and the current placements."""
        before, self.poses_now = self.poses_now, poses
        if self.outputs:
            self._to_outputs(poses=PoseUpdate(poses=poses, frames=frames))
        f = self._names().frames
        if self.recorder is not None and f.robot_pose_frame:  # ("": no poses, as on the ros2 output)
            wall = time.time()
            for robot, sp in poses.items():  # /tf: <robot>/map -> <robot>/base_link, when it moved
                if before.get(robot) != sp:
                    # stamped when the robot was there (as the ros2 output does), logged on arrival
                    self._record(
                        self.recorder.transforms,
                        "/tf",
                        robot_frame(f.robot_map_frame, robot),
                        {robot_frame(f.robot_pose_frame, robot): sp.pose},
                        wall,
                        sp.stamp,
                    )

    def links(self, links: dict[str, Any], robot: str) -> None:
        """The transports' counters, for the recording: on ``/diagnostics``, one status per link
        named ``mapd: <transport> link`` (hardware id: the robot), at ``WARN`` with the faults
        ``mapd status`` shows on it, else ``OK``."""
        if self.recorder is not None:
            self._record(self.recorder.diagnostics, link_diagnostics(links, robot), time.time())

    def _names(self) -> Ros2Names:
        """The topic and frame names of the output that publishes on a ROS 2 graph (the ``ros2``
        output; the defaults without one): a recording played into that graph must agree with it."""
        for o in self.outputs:
            names = o.ros2_names()
            if names is not None:
                return names
        return Ros2Names()

    def status(self) -> dict[str, Any]:
        return {o.name: o.stats() for o in self.outputs}

    def recording(self) -> dict[str, int | bool] | None:
        """The recording's faults and backlog for ``mapd status``, and how many of its oldest files
        were removed to keep it within ``max_total_bytes`` (not a fault); None without one.

        ``failures`` and ``dropped`` are totals since the start; ``writing`` (False while its
        writes fail) and ``behind`` (True while messages are left out) say whether that is now,
        so a disk that filled once is not a fault for the rest of the run."""
        if self.recorder is None:
            return None
        return {
            "failures": self.record_failures,
            "dropped": self.record_dropped,
            "writing": not self._record_outage.failing,
            "behind": self._behind.failing,
            "queued_bytes": self._queued,
            "removed_files": self.recorder.removed,
        }

    # ------------------------------------------------------------------ worker side
    def _to_outputs(
        self,
        update: GlobalUpdate | None = None,
        poses: PoseUpdate | None = None,
        robot_map: tuple[OccupancyGrid, float] | None = None,
    ) -> None:
        """Hand the output thread the newest global map, poses and/or robot map (latest wins, one
        drain queued)."""
        with self._out_lock:
            idle = self._out_next is None and self._pose_next is None and not self._robot_next
            if update is not None:
                self._out_next = update
            if poses is not None:
                self._pose_next = poses
            if robot_map is not None:
                self._robot_next[robot_map[0].robot] = robot_map
        if idle:
            self._out_pool.submit(self._drain_outputs)

    def _drain_outputs(self) -> None:
        with self._out_lock:
            update, self._out_next = self._out_next, None
            poses, self._pose_next = self._pose_next, None
            robot_maps, self._robot_next = self._robot_next, {}
        for o in self.outputs:
            try:
                if update is not None:
                    o.publish(update)
                if poses is not None:
                    o.publish_poses(poses)
                for grid, stamp in robot_maps.values():
                    o.publish_robot_map(grid, stamp)
            except Exception as exc:  # one failing output must not stop the others or the daemon
                log.error("output %s failed: %s: %s", o.name, type(exc).__name__, exc)

    def _record(self, fn: Callable[..., None], *args: Any) -> None:
        size = sum(a.cells for a in args if isinstance(a, OccupancyGrid)) or _SMALL
        with self._queued_lock:
            # One message is always taken (a map over the budget on its own), more only within it.
            behind = self._queued > 0 and self._queued + size > MAX_QUEUED_BYTES
            if not behind:
                self._queued += size
        if behind:
            self.record_dropped += 1
            self._behind.failed(
                f"recording is {self._queued >> 20} MiB behind the disk; messages are left out until it catches up"
            )
            return
        self._behind.recovered(f"recording caught up ({self.record_dropped} messages left out so far)")

        def call() -> None:
            try:
                fn(*args)
            except Exception as exc:  # disk full, a bug: say it once and keep the fleet running
                self.record_failures += 1
                self._record_outage.failed(
                    f"recording failed: {type(exc).__name__}: {exc}; trying each message"
                )
            else:
                self._record_outage.recovered("recording again")
            finally:
                with self._queued_lock:
                    self._queued -= size

        self._files.submit(call)

    def close(self) -> None:
        """Finish what is queued, then write the recording's footer (blocking: call it from a thread)."""
        self._files.shutdown(wait=True)
        self._out_pool.shutdown(wait=True)
        if self.recorder is not None:
            try:
                self.recorder.close()
            except Exception as exc:  # the fleet is stopping anyway: say why the footer is missing
                log.error("recording not closed: %s: %s", type(exc).__name__, exc)
