"""The fusion worker: the asyncio task that owns the global map.

API for the daemon::

    worker = FusionWorker(robot, cfg.fusion, state_dir, on_global=[callback])
    task = asyncio.create_task(worker.run())
    worker.submit(grid)          # own map or a peer's decoded map; grid.robot names it
    worker.status()              # JSON-able dict for `mapd status`
    worker.global_map            # latest OccupancyGrid, or None
    task.cancel()                # stops; a pending update is merged with the held placements first

* ``submit`` never blocks and never queues: the latest map of each robot wins.
* ``run`` loads the previous global map and ``transforms.json`` from the state directory (so a
  restart loses neither the map nor the accepted placements), then waits for submissions. After the
  first new map it waits ``cfg.debounce_s`` (collecting whatever else arrives), places every map with
  a :class:`~mapd.fusion.placement.Placer` and merges them in a worker thread (a large merge never
  stalls the event loop), writes ``global.yaml`` + ``global.pgm`` (map_server files, atomic),
  ``transforms.json`` (atomic: temp file, fsync, rename) and ``owner.npy`` + ``owner.json`` (which
  robot weighed most in each cell, for coloured pictures) into the state directory, and calls every
  ``on_global`` callback with the new grid on the event loop's thread.
* The **fleet frame** is the frame the configured poses are given in, or this robot's own map frame
  when no pose is configured (``cfg.poses``: robot -> ``[x m, y m, yaw rad]`` of that robot's map
  frame in the fleet frame, or ``"estimate"``). The global map's origin lies on the fleet frame's
  cell lattice and only grows outward in blocks of 64 cells (:mod:`mapd.fusion.merge`).
* ``transforms.json`` and ``status()["robots"]`` give, per robot, the "fleet frame -> robot map"
  transform (x, y in meters, yaw in radians, such that ``p_fleet = R(yaw) p_robot_map + (x, y)``),
  its source, confidence, agreement, whether it is merged, and the reason when it is not.
* Until every robot named in a restored ``transforms.json`` has sent a map again, the restored global
  map fills the cells no current map knows, so a restart never shows a half-empty map.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mapd.config import FusionSection
from mapd.errors import FusionError, MapdError, StateError
from mapd.files import WriteOutage, atomic_write_bytes
from mapd.fusion.estimate import EstimateOptions
from mapd.fusion.merge import NO_OWNER, Bounds, MergeResult, extent, merge_with_owner
from mapd.fusion.placement import Placement, Placer, derived_from
from mapd.fusion.transforms import transformed_corners
from mapd.fusion.views import MAX_SIDE
from mapd.grid import (
    DEFAULT_MAX_CELLS,
    UNKNOWN,
    OccupancyGrid,
    Pose2D,
    geometry_problem,
    load_map,
    save_map,
)

log = logging.getLogger(__name__)

GLOBAL_YAML = "global.yaml"
TRANSFORMS_JSON = "transforms.json"
FORMAT = 1


@dataclass(frozen=True)
class _Fused:
    result: MergeResult
    placements: dict[str, Placement]
    seconds: float
    versions: dict[str, int]


class FusionWorker:
    """Owns the global map: re-places and re-merges on every new map version, debounced."""

    def __init__(
        self,
        robot: str,
        cfg: FusionSection,
        state_dir: Path | None,
        on_global: Sequence[Callable[[OccupancyGrid], None]] | None = None,
        *,
        max_cells: int = DEFAULT_MAX_CELLS,
        max_robots: int = 64,
        anchor: str | None = "",
        options: EstimateOptions | None = None,
        admits: Callable[[str], bool] | None = None,
    ) -> None:
        self.robot = robot
        self.cfg = cfg
        self.state_dir = state_dir
        self.on_global: list[Callable[[OccupancyGrid], None]] = list(on_global or [])
        self.max_cells = max_cells
        self.max_robots = max_robots
        poses = {r: (Pose2D(*p) if isinstance(p, list) else None) for r, p in cfg.poses.items()}
        self.placer = Placer(
            poses,
            anchor=robot if anchor == "" else anchor,  # "": this robot's map frame; None: the first map's
            min_confidence=cfg.min_confidence,
            min_agreement=cfg.min_agreement,
            options=options,
        )
        self._latest: dict[str, OccupancyGrid] = {}
        self._wake = asyncio.Event()
        self._global: OccupancyGrid | None = None
        self._placements: dict[str, Placement] = {}
        self._bounds: Bounds | None = None
        self._resolution: float | None = None
        self._restored: OccupancyGrid | None = None
        self._restored_robots: set[str] = set()
        self._merges = 0
        self._last_merge: float | None = None
        self._last_seconds: float | None = None
        self._error: str | None = None
        #: The global map could not be written (said once, not at every merge).
        self._saves = WriteOutage(log)
        self._dropped = 0
        self._loaded = False
        #: Whether a robot's map may be in the global map at all (the roster); others found in the
        #: state directory at start are left out, as :meth:`forget` leaves them out later.
        self._admits = admits or (lambda robot: True)
        self.forgotten = 0
        self._merging = False  # a merge runs on a worker thread (_merge_once)
        self._forget_later: list[str] = []  # robots revoked meanwhile (forget)

    # -- the daemon's side ------------------------------------------------------------------

    def submit(self, grid: OccupancyGrid) -> None:
        """Hand over a map (own or a peer's); ``grid.robot`` names it. Latest wins; never blocks."""
        robot = grid.robot or ""
        if not robot:
            raise FusionError("a map submitted for fusion must name its robot")
        if robot not in self._latest and len(self._latest) >= self.max_robots:
            self._dropped += 1
            log.warning("fusion: ignoring a map from '%s': already %d robots", robot, self.max_robots)
            return
        self._latest[robot] = grid
        self._wake.set()

    def known_pose(self, robot: str, pose: Pose2D) -> None:
        """``robot`` reports where its map frame lies in the fleet frame (its source's start pose).

        Used as a configured pose, unless ``fusion.poses`` names that robot: the config wins. A pose
        that is not finite or lies beyond the bounds of a map origin is ignored with a warning: a
        NaN in it would make every merge fail, freezing the global map for the whole fleet.
        """
        if robot in self.cfg.poses or self.placer.poses.get(robot) == pose:
            return
        problem = geometry_problem(1.0, (pose.x, pose.y, pose.yaw))
        if problem is not None:
            log.warning("fusion: ignoring the start pose reported for '%s': %s", robot, problem)
            return
        self.placer.poses[robot] = pose
        self.placer.reported.add(robot)
        self._wake.set()

    def forget(self, robot: str) -> bool:
        """Take ``robot``'s map out of the global map (it was revoked); False if none was held.

        Its map, placement and reported pose go, and the map is merged again without it. The global
        map held from before the restart goes too if the robot is in it (its cells cannot be told
        from the others'), and so do the bounds, which only ever grew: what is left is built from
        the maps held now, and covers what they cover.
        """
        if robot == self.robot:
            raise FusionError("a robot cannot take its own map out of its global map")
        held = robot in self._latest or robot in self._placements or robot in self._restored_robots
        self._latest.pop(robot, None)
        if self._merging:
            # A merge that began with its map runs on a worker thread, with the placer: the robot
            # is forgotten there once it is back, and its result, which still holds the map, is
            # thrown away (_merge_once), so no global map with it goes out after the revocation.
            self._forget_later.append(robot)
        else:
            self._forget_placement(robot)
        if held:
            self.forgotten += 1
            self._bounds = None
            self._wake.set()
        return held

    def _forget_placement(self, robot: str) -> None:
        """The placement half of :meth:`forget`, on the event loop's thread while no merge runs."""
        self._placements.pop(robot, None)
        again = self.placer.forget(robot)
        if robot == self.placer.anchor:
            self._keep_fleet_frame(robot)  # robots placed in its frame are held where they are
        elif again:
            log.warning(
                "fusion: %s placed against %s's map; estimating afresh from the maps left",
                ", ".join(sorted(again)),
                robot,
            )
        if robot in self._restored_robots:
            self._drop_restored()

    def _keep_fleet_frame(self, anchor: str) -> None:
        """The fleet frame was ``anchor``'s map frame (a base station's first robot, or
        ``fusion.anchor``): keep it where it is, holding the robots placed in it so far as known
        poses, rather than leave every map waiting for a robot that will not come back."""
        pinned = []
        for r, p in self._placements.items():
            if p.accepted and p.transform is not None and r not in self.placer.poses:
                self.placer.pin(r, p.transform)
                pinned.append(r)
        if not self.placer.poses:
            self.placer.anchor = None  # nobody placed yet: the next map fixes a new fleet frame
        log.warning(
            "fusion: the fleet frame was %s's map frame; kept, %s",
            anchor,
            f"with {', '.join(sorted(pinned))} held where they are"
            if pinned
            else "no robot placed in it yet",
        )

    def _drop_restored(self) -> None:
        if self._global is self._restored:
            self._global = None
        self._restored = None
        self._restored_robots = set()

    @property
    def global_map(self) -> OccupancyGrid | None:
        """The latest global map (the restored one until the first merge), or None."""
        return self._global

    @property
    def placements(self) -> dict[str, Placement]:
        return dict(self._placements)

    def status(self) -> dict[str, Any]:
        """JSON-able state for ``mapd status``."""
        g = self._global
        robots: dict[str, Any] = {}
        # A robot revoked while a merge runs keeps its placement until the merge is back; it is
        # gone already for everyone who asks.
        for name in sorted((set(self._latest) | set(self._placements)) - set(self._forget_later)):
            p = self._placements.get(name)
            entry = p.as_dict() if p is not None else Placement(name, reason="not merged yet").as_dict()
            grid = self._latest.get(name)
            entry["version"] = None if grid is None else grid.version
            robots[name] = entry
        return {
            "robot": self.robot,
            "mode": self.cfg.mode,
            "fleet_frame": self.placer.fleet_frame,
            "maps": sum(1 for p in self._placements.values() if p.accepted and p.robot in self._latest),
            "robots": robots,
            "global": None
            if g is None
            else {
                "width": g.width,
                "height": g.height,
                "resolution": g.resolution,
                "origin": {"x": g.origin.x, "y": g.origin.y, "yaw": g.origin.yaw},
                "version": g.version,
            },
            "merges": self._merges,
            "last_merge": self._last_merge,
            "last_merge_s": self._last_seconds,
            "pending": self._wake.is_set(),
            "error": self._error,
            "dropped": self._dropped,
            "revoked": self.forgotten,
            "restored_until": sorted(self._restored_robots - set(self._latest)) if self._restored else [],
        }

    async def run(self) -> None:
        """The worker task: load state, then merge on submissions until cancelled."""
        if not self._loaded:
            await asyncio.to_thread(self._load_state)
            self._loaded = True
        try:
            while True:
                await self._wake.wait()
                if self.cfg.debounce_s > 0:
                    await asyncio.sleep(self.cfg.debounce_s)
                self._wake.clear()
                await self._merge_once(search=True)
        except asyncio.CancelledError:
            if self._wake.is_set() and self._latest:
                # cheap flush: merge what is pending with the placements already held, no estimation
                with contextlib.suppress(Exception):
                    self._wake.clear()
                    await asyncio.to_thread(self._fuse_and_publish_sync, False)
            raise

    async def merge_now(self) -> None:
        """Merge immediately (no debounce); for tools and tests."""
        if not self._loaded:
            await asyncio.to_thread(self._load_state)
            self._loaded = True
        self._wake.clear()
        await self._merge_once(search=True)

    # -- internals --------------------------------------------------------------------------

    async def _merge_once(self, search: bool) -> None:
        maps = dict(self._latest)
        self._merging = True
        job = asyncio.ensure_future(asyncio.to_thread(self._fuse, maps, search))
        try:
            try:
                fused = await asyncio.shield(job)
            except asyncio.CancelledError:
                # A thread cannot be stopped. Wait for it (once; a second cancel is not waited
                # out), so that the stop's flush (run) never shares the placer with it, and it
                # does not save a map after the flush has saved a newer one.
                with contextlib.suppress(BaseException):
                    await asyncio.wait({job})
                    job.exception()  # retrieved: the flush that follows reports its own
                raise
        except MapdError as exc:
            self._error = str(exc)
            log.warning("fusion: %s", exc)
            return
        except Exception as exc:  # a bug must not take the daemon down with the global map
            self._error = f"internal error: {type(exc).__name__}: {exc}"
            log.exception("fusion: merge failed")
            return
        finally:
            self._merging = False
            revoked, self._forget_later = self._forget_later, []
            for robot in revoked:
                self._forget_placement(robot)
        if revoked:
            return  # it holds a revoked map: the next merge (woken by forget) goes without it
        self._apply(fused)

    def _fuse_and_publish_sync(self, search: bool) -> None:
        fused = self._fuse(dict(self._latest), search)
        self._apply(fused, publish=False)

    def _fuse(self, maps: dict[str, OccupancyGrid], search: bool) -> _Fused:
        """Place, merge and persist (runs in a worker thread)."""
        t0 = time.perf_counter()
        self.placer.update(maps, estimate=search)
        # every robot the placer knows, also those restored but not heard from since the restart
        placements = dict(self.placer.placements)
        names = sorted(
            r for r, p in placements.items() if p.accepted and p.transform is not None and r in maps
        )
        names = self._within_extent(maps, placements, names)
        if self._resolution is None:
            first = next((r for r in names if placements[r].source in ("anchor", "pose")), None)
            if first is None and names:
                first = names[0]
            self._resolution = maps[first].resolution if first else None
        names = self._within_cell_limit(maps, placements, names)
        result = merge_with_owner(
            [maps[r] for r in names],
            [placements[r].transform for r in names],
            self.cfg.mode,
            resolution=self._resolution,
            bounds=self._bounds,
            frame_id="fleet",
            max_cells=self.max_cells,
        )
        result = self._fill_from_restored(result, set(maps))
        stamp = time.time()
        grid = result.grid.replace(robot=self.robot, version=self._merges + 1, stamp=stamp)
        result = MergeResult(grid=grid, bounds=result.bounds, owner=result.owner)
        try:
            self._save(result, placements, stamp)
        except MapdError as exc:
            # A full disk must not freeze the fleet's global map: the outputs and status still
            # get the new one, and the state directory keeps the last one written whole (each
            # file is atomic), which a restart restores.
            self._saves.failed(f"fusion: global map not saved (saving again at each merge): {exc}")
        else:
            self._saves.recovered("fusion: global map saved again")
        self._save_owner(result.owner, names)
        return _Fused(result, placements, time.perf_counter() - t0, {r: maps[r].version for r in maps})

    def _within_extent(
        self, maps: dict[str, OccupancyGrid], placements: dict[str, Placement], names: list[str]
    ) -> list[str]:
        """``names`` whose placed maps lie within ``cfg.max_extent_m`` of the fleet frame's origin.

        A map with a corrupt origin (1e6 m) would otherwise make the global map too large to build,
        and every merge would fail until that robot sent a sane version: the whole fleet's map would
        freeze. The others are left out with the reason in their placement; the placer keeps its
        held transform, so the robot's next sane map goes straight back in.
        """
        keep = []
        limit = self.cfg.max_extent_m
        for r in names:
            reach = _reach(maps[r], placements[r])
            if math.isfinite(reach) and reach <= limit:
                keep.append(r)
                continue
            _leave_out(
                placements,
                r,
                f"it reaches {reach:.4g} m from the fleet frame's origin, beyond fusion.max_extent_m = "
                f"{limit:g} m (a damaged map origin or a wrong pose?)",
            )
        return keep

    def _within_cell_limit(
        self, maps: dict[str, OccupancyGrid], placements: dict[str, Placement], names: list[str]
    ) -> list[str]:
        """``names`` less the farthest maps, while the global map would exceed the cell limit.

        Within ``max_extent_m`` a map can still make the global grid bigger than ``max_cells`` (10 km
        at 5 cm is 200,000 cells a side); merging would then fail as a whole, so the maps reaching
        farthest from the fleet frame's origin are left out, with the reason, until the rest fits.
        """
        resolution = self._resolution or 0.05
        keep = list(names)

        while keep:
            box = extent([maps[r] for r in keep], [placements[r].transform for r in keep], resolution)
            if box is not None and self._bounds is not None:
                box = box.union(self._bounds)
            if box is None or (
                box.width * box.height <= self.max_cells and max(box.width, box.height) <= MAX_SIDE
            ):
                break
            far = max(keep, key=lambda r: _reach(maps[r], placements[r]))
            keep.remove(far)
            _leave_out(
                placements,
                far,
                f"with it the global map would be {box.width} x {box.height} cells, over the limit of "
                f"{self.max_cells} cells ({MAX_SIDE} a side)",
            )
        return keep

    def _apply(self, fused: _Fused, publish: bool = True) -> None:
        self._merges = fused.result.grid.version
        self._global = fused.result.grid
        self._bounds = fused.result.bounds
        self._placements = fused.placements
        self._last_merge = fused.result.grid.stamp
        self._last_seconds = fused.seconds
        self._error = None
        if not publish:
            return
        for callback in self.on_global:
            try:
                callback(fused.result.grid)
            except Exception:  # one failing sink must not stop the others or the worker
                log.exception("fusion: an on_global callback failed")

    def _fill_from_restored(self, result: MergeResult, present: set[str]) -> MergeResult:
        """Cells no current map knows keep the restored global map's value until its robots return."""
        old = self._restored
        if old is None:
            return result
        if self._restored_robots <= present:
            self._restored = None
            return result
        ob = Bounds.of_grid(old)
        nb = result.bounds
        if ob is None or old.resolution != result.grid.resolution:
            return result
        c0, r0 = max(ob.c0, nb.c0), max(ob.r0, nb.r0)
        c1, r1 = min(ob.c1, nb.c1), min(ob.r1, nb.r1)
        if c1 <= c0 or r1 <= r0:
            return result
        data = result.grid.data.copy()
        dst = data[r0 - nb.r0 : r1 - nb.r0, c0 - nb.c0 : c1 - nb.c0]
        src = old.data[r0 - ob.r0 : r1 - ob.r0, c0 - ob.c0 : c1 - ob.c0]
        hole = dst == UNKNOWN
        dst[hole] = src[hole]
        return MergeResult(grid=result.grid.replace(data=data), bounds=nb, owner=result.owner)

    # -- state directory --------------------------------------------------------------------

    def _load_state(self) -> None:
        if self.state_dir is None:
            return
        tj = self.state_dir / TRANSFORMS_JSON
        gy = self.state_dir / GLOBAL_YAML
        try:
            doc = json.loads(tj.read_text(encoding="utf-8")) if tj.exists() else None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            log.warning("fusion: ignoring unreadable %s: %s", tj, exc)
            doc = None
        placements: dict[str, Placement] = {}
        if isinstance(doc, dict) and isinstance(doc.get("robots"), dict):
            for name, entry in doc["robots"].items():
                try:
                    placements[str(name)] = Placement.from_dict(entry)
                except (KeyError, TypeError, ValueError) as exc:
                    log.warning("fusion: ignoring entry '%s' of %s: %s", name, tj, exc)
        # Robots off the roster since the last run: their placements go, and a global map built
        # with their maps is not restored (its cells are theirs and the others' alike).
        revoked = sorted(r for r in placements if r != self.robot and not self._admits(r))
        again = sorted(derived_from(placements, set(revoked)))
        in_global = [r for r in revoked if placements.pop(r).accepted]
        for r in again:  # placed against a revoked robot's map: estimated afresh from the others
            placements.pop(r)
        if revoked:
            self.forgotten += len(revoked)
            log.warning(
                "fusion: leaving out %s, no longer on the roster%s%s",
                ", ".join(revoked),
                "; the global map is built afresh" if in_global else "",
                f"; {', '.join(again)}, placed against it, estimated afresh" if again else "",
            )
        if isinstance(doc, dict) and isinstance(doc.get("robots"), dict):
            self._merges = int(doc.get("version", 0)) if isinstance(doc.get("version"), int) else 0
        self.placer.restore(placements)
        self._placements = {r: p for r, p in placements.items()}
        if gy.exists() and not in_global:
            try:
                grid = load_map(gy, max_cells=self.max_cells)
            except MapdError as exc:
                log.warning("fusion: ignoring unreadable %s: %s", gy, exc)
                return
            bounds = Bounds.of_grid(grid)
            if bounds is None:
                log.warning("fusion: %s is not on the fleet lattice; starting a new global map", gy)
                return
            self._global = grid.replace(robot=self.robot, version=self._merges, frame_id="fleet")
            self._bounds = bounds
            self._resolution = grid.resolution
            self._restored = self._global
            self._restored_robots = {r for r, p in placements.items() if p.accepted}

    def _save_owner(self, owner: np.ndarray, names: list[str]) -> None:
        """``owner.npy`` (who contributed each cell, for coloured pictures) and the names it indexes."""
        if self.state_dir is None:
            return
        import io

        buf = io.BytesIO()
        np.save(buf, _owner_names(owner, names))
        try:
            atomic_write_bytes(self.state_dir / "owner.npy", buf.getvalue())
            write_json_atomic(self.state_dir / "owner.json", {"robots": names})
        except OSError as exc:
            log.warning("fusion: cannot write owner map: %s", exc)

    def _save(self, result: MergeResult, placements: dict[str, Placement], stamp: float) -> None:
        if self.state_dir is None:
            return
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StateError(f"{self.state_dir}: cannot create the state directory: {exc.strerror}") from None
        save_map(result.grid, self.state_dir / GLOBAL_YAML)
        doc = {
            "format": FORMAT,
            "robot": self.robot,
            "fleet_frame": self.placer.fleet_frame,
            "units": "x, y in meters, yaw in radians: p_fleet = R(yaw) p_robot_map + (x, y)",
            "mode": self.cfg.mode,
            "version": result.grid.version,
            "stamp": stamp,
            "resolution": result.grid.resolution,
            "origin": list(result.grid.origin),
            "robots": {r: p.as_dict() for r, p in sorted(placements.items())},
        }
        write_json_atomic(self.state_dir / TRANSFORMS_JSON, doc)


def _leave_out(placements: dict[str, Placement], robot: str, why: str) -> None:
    """Mark ``robot``'s placement as left out of the global map, with the reason, and say so once."""
    placements[robot] = replace(
        placements[robot], accepted=False, reason=f"left out of the global map: {why}"
    )
    log.warning("fusion: %s: %s", robot, placements[robot].reason)


def _reach(grid: OccupancyGrid, placement: Placement) -> float:
    """How far from the fleet frame's origin the placed map's farthest corner lies, in meters."""
    assert placement.transform is not None
    c = transformed_corners(grid, placement.transform)
    return float(np.hypot(c[:, 0], c[:, 1]).max())


def _owner_names(owner: np.ndarray, names: list[str]) -> np.ndarray:
    """Per cell, the index into sorted robot names of the map that weighed most (-1: none)."""
    out = np.full(owner.shape, -1, dtype=np.int16)
    valid = owner != NO_OWNER
    out[valid] = owner[valid]
    return out


def write_json_atomic(path: Path, doc: dict[str, Any]) -> None:
    """Write JSON via a temp file, fsync and rename, so readers never see half a file."""
    try:
        payload = (json.dumps(doc, indent=2, allow_nan=False, default=_jsonable) + "\n").encode()
    except (TypeError, ValueError) as exc:
        raise StateError(f"{path}: cannot serialise: {exc}") from None
    try:
        atomic_write_bytes(path, payload)
    except OSError as exc:
        raise StateError(f"{path}: cannot write: {exc.strerror}") from None


def _jsonable(v: object) -> object:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    raise TypeError(f"cannot serialise {type(v).__name__}")


__all__ = ["GLOBAL_YAML", "NO_OWNER", "TRANSFORMS_JSON", "FusionWorker", "write_json_atomic"]
