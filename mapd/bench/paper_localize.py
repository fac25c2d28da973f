"""Figure 9 of the paper: localize the run's own scans in the original and in each recovered map.

Test poses are picked from the run's scans by farthest-point sampling of their positions, so they
spread over the whole map; scans with few returns (under half the beams) are not picked, since the
paper localizes where the lidar sees the building. Each scan is matched with the correlative scan
matcher (:class:`mapd.mapping.localize.ScanMatcher`) in every map from the same start: its true pose plus a
seeded offset, uniform in a disc of ``MAX_OFFSET_M`` and in +-``MAX_OFFSET_DEG``. The matcher
searches a window a little wider than the offset (0.4 m, 12 degrees), so a miss is the map's fault,
not the window's. Errors are reported two ways: against the original map's result (the paper's
comparison, which isolates what compression changes) and against the true (corrected) pose.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from mapd.bench.paper_data import MAX_RANGE, Sample
from mapd.grid import OccupancyGrid, Pose2D
from mapd.mapping.localize import ScanMatcher

MAX_OFFSET_M = 0.3
MAX_OFFSET_DEG = 10.0
SEARCH_XY_M = 0.4
SEARCH_YAW_DEG = 12.0
#: A scan is a candidate test pose when at least this share of its beams return.
MIN_RETURNS = 0.5


def pick_poses(samples: Sequence[Sample], count: int) -> list[int]:
    """Indices of ``count`` samples spread over the map (farthest-point sampling of positions)."""
    ok = [
        i
        for i, s in enumerate(samples)
        if np.count_nonzero(np.isfinite(s.ranges) & (s.ranges > 0) & (s.ranges < MAX_RANGE))
        >= MIN_RETURNS * len(s.ranges)
    ]
    if not ok:
        return []
    xy = np.array([[samples[i].truth.x, samples[i].truth.y] for i in ok])
    # Start from the candidate farthest from the centroid: deterministic and on the map's edge.
    chosen = [int(np.argmax(np.hypot(*(xy - xy.mean(axis=0)).T)))]
    dist = np.hypot(*(xy - xy[chosen[0]]).T)
    while len(chosen) < min(count, len(ok)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.hypot(*(xy - xy[nxt]).T))
    return [ok[i] for i in chosen]


def start_offsets(count: int, seed: int) -> np.ndarray:
    """(count, 3) seeded offsets (dx m, dy m, dyaw rad): uniform in the disc and the yaw interval."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x9A9E]))
    r = MAX_OFFSET_M * np.sqrt(rng.random(count))
    a = rng.uniform(-math.pi, math.pi, count)
    yaw = np.radians(MAX_OFFSET_DEG) * rng.uniform(-1.0, 1.0, count)
    return np.stack([r * np.cos(a), r * np.sin(a), yaw], axis=1)


def localize(
    maps: dict[str, OccupancyGrid], samples: Sequence[Sample], picks: Sequence[int], offsets: np.ndarray
) -> dict[str, np.ndarray]:
    """Map name -> (n, 4) array of localized x, y, yaw and match score, one row per picked sample."""
    out: dict[str, np.ndarray] = {}
    for name, grid in maps.items():
        matcher = ScanMatcher(grid)
        rows = []
        for j, (idx, off) in enumerate(zip(picks, offsets, strict=True)):
            s = samples[idx]
            guess = Pose2D(s.truth.x + off[0], s.truth.y + off[1], s.truth.yaw + off[2])
            m = matcher.match(
                s.ranges,
                s.angles,
                guess,
                max_range=MAX_RANGE,
                search_xy=SEARCH_XY_M,
                search_yaw=math.radians(SEARCH_YAW_DEG),
            )
            rows.append([m.pose.x, m.pose.y, m.pose.yaw, m.score])
            print(f"\rfig 9: {name} map, pose {j + 1}/{len(picks)}", end="", file=sys.stderr, flush=True)
        out[name] = np.array(rows, dtype=np.float64).reshape(-1, 4)
    print(file=sys.stderr)
    return out


def pose_errors(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(n, 3) errors x m, y m, yaw rad of poses ``est`` against ``ref`` (yaw wrapped to +-pi)."""
    d = est[:, :3] - ref[:, :3]
    d[:, 2] = np.arctan2(np.sin(d[:, 2]), np.cos(d[:, 2]))
    return d


def error_stats(err: np.ndarray) -> dict[str, float]:
    """Mean, median, 95th percentile and largest absolute error: x, y in cm, yaw in degrees."""
    if len(err) == 0:
        return {}
    a = np.abs(err) * np.array([100.0, 100.0, math.degrees(1.0)])
    out: dict[str, float] = {}
    for k, col in (("x_cm", 0), ("y_cm", 1), ("yaw_deg", 2)):
        v = a[:, col]
        out[f"mean_{k}"] = float(v.mean())
        out[f"median_{k}"] = float(np.median(v))
        out[f"p95_{k}"] = float(np.percentile(v, 95))
        out[f"max_{k}"] = float(v.max())
    out["mean_xy_cm"] = float(np.hypot(a[:, 0], a[:, 1]).mean())
    return out


def evaluate(
    maps: dict[str, OccupancyGrid],
    samples: Sequence[Sample],
    count: int,
    seed: int,
    truth_label: str = "corrected pose",
) -> dict[str, Any]:
    """Pick the poses, localize in every map (the first is the original) and summarize the errors.

    Rows compare each recovered map's poses with the original map's ("original map") and every
    map's with the samples' poses (``truth_label``).
    """
    picks = pick_poses(samples, count)
    offsets = start_offsets(len(picks), seed)
    found = localize(maps, samples, picks, offsets)
    truth = np.array([[samples[i].truth.x, samples[i].truth.y, samples[i].truth.yaw] for i in picks])
    truth = truth.reshape(-1, 3)
    original = next(iter(maps))
    rows: list[dict[str, Any]] = []
    per_pose: list[dict[str, Any]] = []
    for name, est in found.items():
        refs = [(truth_label, truth)]
        if name != original:
            refs.insert(0, ("original map", found[original]))
        score = float(est[:, 3].mean()) if len(est) else math.nan
        for against, ref in refs:
            stats = error_stats(pose_errors(est, ref))
            rows.append({"map": name, "against": against, "poses": len(est), "score": score, **stats})
    for j, idx in enumerate(picks):
        row: dict[str, Any] = {
            "pose": j,
            "stamp": samples[idx].stamp,
            "x": truth[j, 0],
            "y": truth[j, 1],
            "yaw": truth[j, 2],
            "start_dx": offsets[j, 0],
            "start_dy": offsets[j, 1],
            "start_dyaw": offsets[j, 2],
        }
        for name, est in found.items():
            row.update({f"{name}_x": est[j, 0], f"{name}_y": est[j, 1], f"{name}_yaw": est[j, 2]})
            row[f"{name}_score"] = est[j, 3]
        per_pose.append(row)
    return {
        "rows": rows,
        "poses": per_pose,
        "found": found,
        "truth": truth,
        "truth_label": truth_label,
        "original": original,
    }
