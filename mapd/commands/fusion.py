"""``mapd merge``: fuse map_server maps into one, with known poses, estimated ones, or both."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapd.commands.common import path_or_stdio
from mapd.errors import ConfigError

if TYPE_CHECKING:
    from mapd.grid import OccupancyGrid, Pose2D

#: Exit status of a merge that wrote its output but left some input maps out of it (each listed,
#: with why): scripts can tell a partial merge from a whole one without parsing the output.
EXIT_LEFT_OUT = 3

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
--min-agreement is left out of the merge, and the output says why. When the first map has no
--pose and matches no posed map, the output is in the frame of the --pose options instead, and
everything printed says so. --json lists every input under "maps" (and those after the first under
"transforms"): "accepted" is whether its cells are in the output, "reason" why not.

exit status: 0 every map merged; 3 the output was written but some maps were left out (listed on
stderr, and in "left_out" with --json); 2 a bad option (an output naming an input file, a --pose
for no input, ...; nothing is written); 1 another error (an unreadable map, a full disk, ...).

examples:
  mapd merge intel_part1.yaml intel_part2.yaml -o merged.yaml --png merged.png
  mapd merge a.yaml b.yaml c.yaml -o out.yaml --pose 0=0,0,0 --pose 1=12.5,-3,1.5708 --json
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "merge",
        help="fuse map_server maps into one (known poses, estimated ones, or both)",
        description="Place every map in the first map's frame (by --pose, or by estimating it from the "
        "maps' overlap; in the frame of the --pose options when the first map cannot be placed) and "
        "merge them into one map_server map.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "maps", nargs="+", type=path_or_stdio, metavar="MAP.yaml", help="map_server YAML files (at least two)"
    )
    p.add_argument(
        "-o", "--output", type=path_or_stdio, required=True, help="map_server YAML to write the merged map to"
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
    p.add_argument(
        "--png", type=path_or_stdio, help="also write a colour preview (each map's cells in its colour)"
    )
    p.add_argument(
        "--json", action="store_true", help="print the report as JSON: frame, maps, left_out, transforms"
    )
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


def _lattice_of(grid: OccupancyGrid) -> Pose2D:
    """Where a frame whose lattice holds ``grid``'s cells lies in ``grid``'s frame: moved by what
    its origin has past a whole cell (identity for an origin on the lattice, or one turned by a yaw,
    whose cells no lattice of the frame holds)."""
    from mapd.grid import Pose2D

    def past(v: float, r: float) -> float:
        rest = v - r * round(v / r)
        return 0.0 if abs(rest) < 1e-9 * r else rest  # on the lattice but for float rounding

    o = grid.origin
    if o.yaw != 0.0:
        return Pose2D(0.0, 0.0, 0.0)
    return Pose2D(past(o.x, grid.resolution), past(o.y, grid.resolution), 0.0)


def cmd_merge(args: argparse.Namespace) -> int:
    from mapd.commands.common import check_writable, map_inputs, map_outputs, refuse_overwrite, refuse_stdio
    from mapd.fusion.merge import NO_OWNER, merge_with_owner, save_png
    from mapd.fusion.placer import Placer
    from mapd.fusion.transforms import IDENTITY, compose, inverse
    from mapd.grid.load import load_map
    from mapd.grid.save import save_map

    if len(args.maps) < 2:
        raise ConfigError("merge needs at least two maps")
    if len(args.maps) >= NO_OWNER:  # said now, not after every map was placed against the others
        raise ConfigError(f"merge takes at most {NO_OWNER - 1} maps, not {len(args.maps)}")
    for path in args.maps:
        refuse_stdio(path, "a map to merge")
    refuse_stdio(args.output, "-o")
    refuse_stdio(args.png, "--png")
    outputs = map_outputs(args.output, "-o")
    if args.png is not None:
        if args.png.resolve() in {p.resolve() for p, _ in outputs}:  # the preview over the merged map
            raise ConfigError(f"--png {args.png}: that is the merged map's own file; name the preview apart")
        outputs.append((args.png, f"--png {args.png}"))
    for name, v in (("--min-confidence", args.min_confidence), ("--min-agreement", args.min_agreement)):
        if not (0.0 <= v <= 1.0):
            raise ConfigError(f"{name} must lie in [0, 1], got {v}")
    names = robot_names(args.maps)
    poses = parse_poses(args.pose, names)
    # Before any map is placed (minutes) and before anything is written: an output over an input
    # (map YAML or the image it names) destroyed it, and a bad --png came up after the merged map
    # was written.
    refuse_overwrite(outputs, [f for path in args.maps for f in map_inputs(path, "the input map")])
    check_writable(args.output, "-o")
    if args.png is not None:
        check_writable(args.png, "--png")
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
    placed = [n for n in names if placements[n].accepted and placements[n].transform is not None]
    # The output is in the first map's frame when that map is placed (by --pose or as the anchor);
    # when it is not (only other maps have a --pose, and it matched none of them), the output stays
    # in the frame of the --pose options, and so do the transforms reported.
    first = placements[names[0]]
    t_first = first.transform if names[0] in placed else None
    back = inverse(t_first) if t_first is not None else IDENTITY
    if t_first is not None:
        frame = f"map frame of {names[0]}"
        units = "x, y in meters, yaw in radians: p_first = R(yaw) p_input + (x, y)"
    else:
        frame = "frame of the --pose options (" + ", ".join(sorted(poses)) + ")"
        units = "x, y in meters, yaw in radians: p_pose_frame = R(yaw) p_input + (x, y)"
    in_frame = {n: compose(back, placements[n].transform) for n in placed}  # type: ignore[arg-type]
    # The merge lays cells on its frame's lattice (multiples of the resolution from the origin): a
    # first map whose origin is off it (x = 0.025 at 5 cm) came back resampled, up to half a cell
    # off. Merged in a frame moved by that remainder, the first map's cells stay as they are.
    lattice = _lattice_of(maps[names[0]]) if names[0] in in_frame else IDENTITY
    result = merge_with_owner(
        [maps[n] for n in names],
        [compose(inverse(lattice), in_frame[n]) if n in in_frame else None for n in names],
        args.mode,
        resolution=maps[names[0]].resolution,
        chunk=1,  # one-shot: no later merge to keep the size steady for, so no 64-cell blocks
        frame_id="map",
    )
    refused = {names[i]: why for i, why in result.left_out}  # placed, but the merge could not take it
    grid = result.grid.replace(origin=compose(lattice, result.grid.origin))
    save_map(grid, args.output)
    if args.png:
        save_png(result, str(args.png))

    rows: list[dict[str, Any]] = []
    for i, n in enumerate(names):
        p = placements[n]
        rel_t = in_frame.get(n)
        merged = rel_t is not None and n not in refused
        reason = refused.get(n, p.reason) if not merged else p.reason
        rows.append(
            {
                "robot": n,
                "map": str(args.maps[i]),
                "x": None if rel_t is None else rel_t.x,
                "y": None if rel_t is None else rel_t.y,
                "yaw": None if rel_t is None else rel_t.yaw,
                "confidence": round(p.confidence, 4),
                "agreement": None if p.agreement is None else round(p.agreement, 4),
                "accepted": merged,  # its cells are in the output
                "source": p.source,
                "reason": reason,
            }
        )
    merged_rows = [r for r in rows if r["accepted"]]
    left_out = [r for r in rows if not r["accepted"]]
    doc = {
        "output": str(args.output),
        "frame": frame,
        "units": units,
        # every input after the first (the first map's row is in "maps"), as before
        "transforms": rows[1:],
        "maps": rows,
        "left_out": [r["robot"] for r in left_out],
        "global": {
            "width": grid.width,
            "height": grid.height,
            "resolution": grid.resolution,
            "origin": list(grid.origin),
            "maps_merged": len(merged_rows),
            "maps_left_out": len(left_out),
        },
    }
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(
            f"{args.output}: {grid.width} x {grid.height} cells, {len(merged_rows)} of {len(names)} maps merged"
        )
        why = "" if t_first is not None else f", as the first map {names[0]} is not placed"
        print(f"transforms in the {frame}{why} (meters, degrees):")
        for r in rows:
            if not r["accepted"]:
                print(f"  {r['robot']:<20} not merged: {r['reason']}")
            else:
                print(
                    f"  {r['robot']:<20} x {r['x']:9.3f}  y {r['y']:9.3f}  yaw {math.degrees(r['yaw']):8.2f}  "
                    f"confidence {r['confidence']:.2f}  agreement "
                    f"{'-' if r['agreement'] is None else format(r['agreement'], '.2f')}  ({r['source']})"
                )
    if left_out:
        print(
            f"mapd merge: {len(left_out)} of {len(names)} maps left out of {args.output}: "
            + "; ".join(f"{r['robot']}: {r['reason']}" for r in left_out),
            file=sys.stderr,
        )
        return EXIT_LEFT_OUT
    return 0
