"""One simulated robot: route planning, driving, lidar and mapping, with no clock and no I/O.

:class:`SimRobot` is the core the ``sim`` source wraps. Each :meth:`SimRobot.step` advances sim time
by one scan period: the robot turns and drives along its route, takes a lidar scan and feeds it to
the shared :class:`~mapd.mapping.mapper.Mapper` in its own map frame (its start pose). Everything is drawn
from ``(seed, index)``, so two processes given the same world and seed produce the same maps, and
robot ``i`` of ``N`` never needs to hear from the others.

Routes: the world's goals (room centres and corridor points, or spread-out free points of a loaded
map) are cut into ``robots`` groups along the building's long axis. Robot ``i`` visits its own group
first (nearest goal next), then the others, then starts over. Paths come from Dijkstra
(:func:`scipy.sparse.csgraph.dijkstra`) on a coarse grid of cells with enough clearance, weighted to
keep to the middle of corridors and doors, and are straightened by line-of-sight shortcuts.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid, Pose2D
from mapd.mapping.lidar import Lidar
from mapd.mapping.mapper import Mapper, MapperOptions, relative
from mapd.mapping.worldgen import World

PLAN_CELL = 0.2  # m, planner grid


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


class Planner:
    """Shortest well-clear paths on a world, on a coarse grid (cells of PLAN_CELL meters)."""

    def __init__(self, world: World, clearance: float) -> None:
        g = world.grid
        self.world = world
        res = g.resolution
        self.clear = ndimage.distance_transform_edt(world.free()) * res  # m to the nearest non-free cell
        self.clearance = clearance
        k = max(1, round(PLAN_CELL / res))
        self.k = k
        h, w = (g.height // k) * k, (g.width // k) * k
        coarse = self.clear[:h, :w].reshape(h // k, k, w // k, k).min(axis=(1, 3))
        self.coarse_clear = coarse
        ok = coarse >= clearance
        self.ok = ok
        self.ch, self.cw = ok.shape
        # 8-connected graph over traversable coarse cells; staying central costs less.
        cost = 1.0 + 0.6 / np.minimum(np.maximum(coarse, 1e-3), 1.5)
        ids = np.arange(ok.size).reshape(ok.shape)
        rows_u: list[np.ndarray] = []
        rows_v: list[np.ndarray] = []
        weights: list[np.ndarray] = []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            # Pairs (r, c) -> (r + dr, c + dc) with both cells inside the grid.
            c0, c1 = max(0, -dc), self.cw - max(0, dc)
            both = ok[: self.ch - dr, c0:c1] & ok[dr:, c0 + dc : c1 + dc]
            ia = ids[: self.ch - dr, c0:c1][both]
            ib = ids[dr:, c0 + dc : c1 + dc][both]
            step = math.hypot(dr, dc) * PLAN_CELL
            rows_u.append(ia)
            rows_v.append(ib)
            weights.append(step * 0.5 * (cost.ravel()[ia] + cost.ravel()[ib]))
        u = np.concatenate(rows_u)
        v = np.concatenate(rows_v)
        wt = np.concatenate(weights)
        self.graph = sparse.csr_matrix((wt, (u, v)), shape=(ok.size, ok.size))
        # Nearest traversable coarse cell for every coarse cell (to snap starts and goals).
        self._near = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)

    def _cell(self, x: float, y: float) -> int | None:
        fr, fc = self.world.grid.world_to_cell(np.array(x), np.array(y))
        r = int(np.clip(np.floor(float(fr) / self.k), 0, self.ch - 1))
        c = int(np.clip(np.floor(float(fc) / self.k), 0, self.cw - 1))
        if not self.ok.any():
            return None
        nr, nc = int(self._near[0][r, c]), int(self._near[1][r, c])
        return nr * self.cw + nc

    def _centre(self, node: int) -> tuple[float, float]:
        r, c = divmod(node, self.cw)
        # Centre of the coarse cell in fine-cell units (cell_to_world adds half a cell), then to world.
        fx, fy = self.world.grid.cell_to_world(
            np.array((r + 0.5) * self.k - 0.5), np.array((c + 0.5) * self.k - 0.5)
        )
        return float(fx), float(fy)

    def visible(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        """True when the straight segment a-b keeps the clearance everywhere."""
        g = self.world.grid
        n = max(2, int(math.hypot(b[0] - a[0], b[1] - a[1]) / (0.5 * g.resolution)) + 1)
        t = np.linspace(0.0, 1.0, n)
        fr, fc = g.world_to_cell(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
        r = np.floor(fr).astype(np.int64)
        c = np.floor(fc).astype(np.int64)
        if r.min() < 0 or c.min() < 0 or r.max() >= g.height or c.max() >= g.width:
            return False
        return bool((self.clear[r, c] >= self.clearance * 0.999).all())

    def path(self, start: tuple[float, float], goal: tuple[float, float]) -> list[tuple[float, float]] | None:
        """Waypoints from ``start`` to ``goal`` (start excluded), or None when unreachable."""
        s, t = self._cell(*start), self._cell(*goal)
        if s is None or t is None:
            return None
        if s == t:
            return [goal]
        _dist, pred = csgraph.dijkstra(self.graph, directed=False, indices=s, return_predecessors=True)
        if pred[t] < 0:
            return None
        nodes = [t]
        while nodes[-1] != s:
            nodes.append(int(pred[nodes[-1]]))
        nodes.reverse()
        pts = [start] + [self._centre(n) for n in nodes[1:-1]] + [self._centre(t)]
        if self.visible(pts[-1], goal):
            pts.append(goal)
        # Greedy line-of-sight shortcuts: from each anchor jump to the farthest point still visible.
        out: list[tuple[float, float]] = []
        i = 0
        while i < len(pts) - 1:
            j = i + 1
            while j + 1 < len(pts) and self.visible(pts[i], pts[j + 1]):
                j += 1
            out.append(pts[j])
            i = j
        return out


class SimRobot:
    """Robot ``index`` of ``robots`` driving through ``world`` and mapping it; advance with :meth:`step`."""

    def __init__(
        self,
        world: World,
        *,
        seed: int = 0,
        index: int = 0,
        robots: int = 1,
        start: Pose2D | str = "auto",
        mapper: MapperOptions | None = None,
        lidar: dict[str, Any] | None = None,
        speed: float = 0.8,
        turn_rate: float = 1.5,
        scan_rate: float = 5.0,
        radius: float = 0.25,
        max_cells: int = DEFAULT_MAX_CELLS,
    ) -> None:
        if not 0 <= index < robots:
            raise ValueError(f"index {index} is not in 0..{robots - 1}")
        self.world = world
        self.index, self.robots = index, robots
        self.speed, self.turn_rate = speed, turn_rate
        self.dt = 1.0 / scan_rate
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, index, 0x11DA]))
        self.planner = Planner(world, clearance=radius + 0.05)
        lopts = dict(lidar or {})
        g = world.grid
        self.lidar = Lidar(world.occupied(), g.resolution, g.origin, **lopts)
        self.mapper = Mapper(mapper, max_cells=max_cells)
        self.groups = self._groups()
        if isinstance(start, Pose2D):
            self.start = start
        elif start == "random":
            self.start = self._random_start()
        elif start == "auto":
            self.start = self._auto_start()
        else:
            raise ValueError(f"start must be a pose, 'auto' or 'random', not {start!r}")
        self.pose = self.start
        self.time = 0.0
        self.steps = 0
        self.distance = 0.0
        self._route: list[tuple[float, float]] = []
        self._tour = self._tour_from(self.start)
        self._tour_pos = 0
        self.goals_reached = 0

    # -- routes --------------------------------------------------------------------------------------
    def _groups(self) -> list[list[tuple[float, float]]]:
        goals = [gl for gl in self.world.goals if self.planner._cell(*gl) is not None]
        g = self.world.grid
        wide = g.width >= g.height
        goals.sort(key=lambda p: (p[0], p[1]) if wide else (p[1], p[0]))
        n = self.robots
        return [goals[(i * len(goals)) // n : ((i + 1) * len(goals)) // n] for i in range(n)]

    def _auto_start(self) -> Pose2D:
        w = self.world
        if w.corridor is not None:
            x0, x1, y = w.corridor
            x = x0 + (self.index + 0.5) * (x1 - x0) / self.robots
            return Pose2D(x, y, 0.0)
        own = self.groups[self.index] or [gl for grp in self.groups for gl in grp]
        if not own:
            return self._random_start()
        x, y = own[0]
        return Pose2D(x, y, 0.0)

    def _random_start(self) -> Pose2D:
        ok = self.planner.clear >= self.planner.clearance
        cells = np.flatnonzero(ok)
        if cells.size == 0:
            raise ValueError("the world has no free space a robot fits in")
        rows, cols = np.divmod(cells[int(self.rng.integers(cells.size))], ok.shape[1])
        x, y = self.world.grid.cell_to_world(np.array(rows), np.array(cols))
        return Pose2D(float(x), float(y), float(self.rng.uniform(-math.pi, math.pi)))

    def _tour_from(self, here: Pose2D) -> list[tuple[float, float]]:
        """Own group nearest-first, then the other groups (nearest group first), nearest-first each."""
        others = sorted((i for i in range(self.robots) if i != self.index), key=lambda i: abs(i - self.index))
        order = [self.index, *others]
        tour: list[tuple[float, float]] = []
        x, y = here.x, here.y
        for gi in order:
            left = list(self.groups[gi])
            while left:
                j = min(range(len(left)), key=lambda k: (left[k][0] - x) ** 2 + (left[k][1] - y) ** 2)
                x, y = left.pop(j)
                tour.append((x, y))
        return tour

    def _next_route(self) -> None:
        for _ in range(len(self._tour)):
            goal = self._tour[self._tour_pos % len(self._tour)]
            self._tour_pos += 1
            path = self.planner.path((self.pose.x, self.pose.y), goal)
            if path:
                self._route = path
                return

    # -- motion and sensing --------------------------------------------------------------------------
    def _drive(self, budget: float) -> None:
        x, y, yaw = self.pose
        while budget > 1e-9:
            if not self._route:
                self._next_route()
                if not self._route:
                    # Nowhere to go: turn on the spot so the lidar still sweeps.
                    yaw = _wrap(yaw + self.turn_rate * budget)
                    break
            gx, gy = self._route[0]
            dist = math.hypot(gx - x, gy - y)
            if dist < 1e-6:
                self._route.pop(0)
                if not self._route:
                    self.goals_reached += 1
                continue
            err = _wrap(math.atan2(gy - y, gx - x) - yaw)
            if abs(err) > 1e-6:
                turn = min(abs(err), self.turn_rate * budget)
                yaw = _wrap(yaw + math.copysign(turn, err))
                budget -= turn / self.turn_rate
                continue
            move = min(dist, self.speed * budget)
            x += move * math.cos(yaw)
            y += move * math.sin(yaw)
            self.distance += move
            budget -= move / self.speed
        self.pose = Pose2D(x, y, yaw)

    def step(self) -> None:
        """Advance one scan period: drive, scan, map."""
        self._drive(self.dt)
        self.steps += 1
        # From the step count, so sim time does not drift with float sums.
        self.time = self.steps * self.dt
        ranges = self.lidar.scan(self.pose, self.rng)
        self.mapper.integrate(ranges, self.lidar.angles, relative(self.start, self.pose))

    def snapshot(self, *, robot: str = "", version: int = 0) -> OccupancyGrid:
        """The robot's map so far, in its own map frame (its start pose), stamped with sim time."""
        return self.mapper.snapshot(robot=robot, version=version, stamp=self.time)
