"""``mapd merge``: fuse map_server maps into one, with known poses, estimated ones, or both."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from mapd.errors import ConfigError

EPILOG = """\
Robots are named by their map file's stem (intel_part1.yaml -> intel_part1) when the stems are all
different, and always also by their position among the inputs, counting from 0 (use that when
several inputs are all called map.yaml).

--pose ROBOT=x,y,yaw gives ROBOT's map frame in the fleet frame: x and y in meters, yaw in radians
(the robot's starting pose, for a map that starts where the robot starts; not the origin of the
map's cell (0,0), which the map's yaml already gives). Without any --pose the fleet frame is the
first map's frame; maps without a pose are estimated against the maps already placed.

Every transform printed is the input's map frame expressed in the FIRST map's frame
(p_first = R(yaw) p_input + (x, y)). An input whose estimate is below --min-confidence or
--min-agreement is left out of the merge, and the output says why.

examples:
  mapd merge intel_part1.yaml intel_part2.yaml -o merged.yaml --png merged.png
  mapd merge a.yaml b.yaml c.yaml -o out.yaml --pose 0=0,0,0 --pose 1=12.5,-3,1.5708 --json
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "merge",
        help="fuse map_server maps into one (known poses, estimated ones, or both)",
        description="Place every map in the first map's frame (by --pose, or by estimating it from the "
        "maps' overlap) and merge them into one map_server map.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "maps", nargs="+", type=Path, metavar="MAP.yaml", help="map_server YAML files (at least two)"
    )
    p.add_argument(
        "-o", "--output", type=Path, required=True, help="map_server YAML to write the merged map to"
    )
    p.add_argument(
        "--pose",
        action="append",
        default=[],
        metavar="ROBOT=x,y,yaw",
        help="a known pose: ROBOT's map frame in the fleet frame (meters, meters, radians); repeatable",
    )
    p.add_argument("--mode", choices=("logodds", "occupied_wins"), default="logodds", help="merge rule")
    p.add_argument("--min-confidence", type=float, default=0.5, help="accept estimates at or above this")
    p.add_argument("--min-agreement", type=float, default=0.8, help="overlap agreement needed to accept")
    p.add_argument("--png", type=Path, help="also write a colour preview (each map's cells in its colour)")
    p.add_argument("--json", action="store_true", help="print the transforms as JSON")
    p.set_defaults(func=cmd_merge)


def robot_names(paths: list[Path]) -> list[str]:
    """File stems when they are unique, else positions ("0", "1", ...)."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems) and not any(s.isdigit() for s in stems):
        return stems
    return [str(i) for i in range(len(paths))]


def parse_poses(specs: list[str], names: list[str]) -> dict[str, Any]:
    """``ROBOT=x,y,yaw`` strings to robot name -> Pose2D (ROBOT may be a name or a position)."""
    from mapd.grid import Pose2D

    out: dict[str, Any] = {}
    for spec in specs:
        robot, sep, values = spec.partition("=")
        robot = robot.strip()
        if not sep or not robot:
            raise ConfigError(f"--pose {spec!r}: expected ROBOT=x,y,yaw")
        if robot not in names:
            if robot.isdecimal() and int(robot) < len(names):  # ("²".isdigit(), but int() refuses it)
                robot = names[int(robot)]
            else:
                raise ConfigError(
                    f"--pose {spec!r}: no input named '{robot}' (names: {', '.join(names)}, or 0..{len(names) - 1})"
                )
        try:
            x, y, yaw = (float(v) for v in values.split(","))
        except ValueError:
            raise ConfigError(
                f"--pose {spec!r}: expected three numbers x,y,yaw (meters, meters, radians)"
            ) from None
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise ConfigError(f"--pose {spec!r}: the numbers must be finite")
        if robot in out:
            raise ConfigError(f"--pose: '{robot}' is given twice")
        out[robot] = Pose2D(x, y, yaw)
    return out


def cmd_merge(args: argparse.Namespace) -> int:
    from mapd.fusion.merge import NO_OWNER, merge_with_owner, save_png
    from mapd.fusion.placement import Placer
    from mapd.fusion.transforms import IDENTITY, compose, inverse
    from mapd.grid import load_map, save_map

    if len(args.maps) < 2:
        raise ConfigError("merge needs at least two maps")
    if len(args.maps) >= NO_OWNER:  # said now, not after every map was placed against the others
        raise ConfigError(f"merge takes at most {NO_OWNER - 1} maps, not {len(args.maps)}")
    if args.png is not None:
        outputs = {args.output.resolve(), args.output.with_suffix(".pgm").resolve()}
        if args.png.resolve() in outputs:  # the preview would be written over the merged map
            raise ConfigError(f"--png {args.png}: that is the merged map's own file; name the preview apart")
    for name, v in (("--min-confidence", args.min_confidence), ("--min-agreement", args.min_agreement)):
        if not (0.0 <= v <= 1.0):
            raise ConfigError(f"{name} must lie in [0, 1], got {v}")
    names = robot_names(args.maps)
    poses = parse_poses(args.pose, names)
    maps = {n: load_map(p, robot=n) for n, p in zip(names, args.maps, strict=True)}
    placer = Placer(
        poses, anchor=names[0], min_confidence=args.min_confidence, min_agreement=args.min_agreement
    )
    # Each map is tried against every map placed before it (the best fit wins), so a merge of many
    # maps takes minutes: a progress bar on a terminal says how far it is.
    from tqdm import tqdm

    with tqdm(total=len(names) - 1, desc="placing maps", unit=" map", disable=None, leave=False) as bar:

        def tried(p: Any) -> None:
            bar.set_postfix_str(f"{p.robot}: {'placed' if p.accepted else 'not yet'}")
            bar.update(1 if p.accepted else 0)

        placements = placer.update(maps, tried=tried)
    merged = [n for n in names if placements[n].accepted and placements[n].transform is not None]
    # The output is in the first map's frame (the fleet frame unless poses define another one);
    # when the first map could not be placed, it stays in the fleet frame.
    first = placements[names[0]]
    t_first = first.transform if first.accepted else None
    back = inverse(t_first) if t_first is not None else IDENTITY
    result = merge_with_owner(
        [maps[n] for n in names],
        [compose(back, placements[n].transform) if n in merged else None for n in names],  # type: ignore[arg-type]
        args.mode,
        resolution=maps[names[0]].resolution,
        frame_id="map",
    )
    grid = result.grid
    save_map(grid, args.output)
    if args.png:
        save_png(result, str(args.png))

    rows: list[dict[str, Any]] = []
    for i, n in enumerate(names):
        p = placements[n]
        rel_t = None
        if t_first is not None and p.accepted and p.transform is not None:
            rel_t = compose(inverse(t_first), p.transform)
        reason = p.reason
        if p.accepted and t_first is None:
            reason = f"{reason}; the first map is not placed, so no transform in its frame"
        rows.append(
            {
                "robot": n,
                "map": str(args.maps[i]),
                "x": None if rel_t is None else rel_t.x,
                "y": None if rel_t is None else rel_t.y,
                "yaw": None if rel_t is None else rel_t.yaw,
                "confidence": round(p.confidence, 4),
                "agreement": None if p.agreement is None else round(p.agreement, 4),
                "accepted": bool(p.accepted and rel_t is not None),
                "source": p.source,
                "reason": reason,
            }
        )
    doc = {
        "output": str(args.output),
        "frame": f"map frame of {names[0]}",
        "units": "x, y in meters, yaw in radians: p_first = R(yaw) p_input + (x, y)",
        "transforms": rows[1:],
        "global": {
            "width": grid.width,
            "height": grid.height,
            "resolution": grid.resolution,
            "origin": list(grid.origin),
            "maps_merged": len(merged),
        },
    }
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(f"{args.output}: {grid.width} x {grid.height} cells, {len(merged)} of {len(names)} maps merged")
        print(f"transforms in the map frame of {names[0]} (meters, degrees):")
        for r in rows[1:]:
            if r["x"] is None:
                print(f"  {r['robot']:<20} not merged: {r['reason']}")
            else:
                print(
                    f"  {r['robot']:<20} x {r['x']:9.3f}  y {r['y']:9.3f}  yaw {math.degrees(r['yaw']):8.2f}  "
                    f"confidence {r['confidence']:.2f}  agreement "
                    f"{'-' if r['agreement'] is None else format(r['agreement'], '.2f')}  ({r['source']})"
                )
    if len(merged) < len(names):
        print(
            f"mapd merge: {len(names) - len(merged)} map(s) left out (not confidently placed)",
            file=sys.stderr,
        )
    return 0
