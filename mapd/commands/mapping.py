"""``mapd replay``: turn a CARMEN log into the growing map snapshots robots would have sent."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from mapd.bench.common import float_arg

#: The longest usable lidar range (m) --max-range takes; ``inf`` is what leaving it out means.
MAX_RANGE_M = 1000.0


def _resolution(text: str) -> float:
    """``--resolution``, checked by the mapper's rule; imported when given (numpy and pydantic
    would otherwise load at every ``mapd`` start)."""
    from mapd.mapping.mapper import resolution_arg

    return resolution_arg(text)


#: What a replay writes into its output folder: a second run into the same folder left the first
#: run's extra snapshots (and robots) beside its own, so such a folder is refused.
_REPLAY_DIR = re.compile(r"robot\d+")


def _check_output(out: Path) -> None:
    """Refuse ``-o`` when it is not a folder, or holds an earlier replay's files; before any work.

    Overwriting in place would mix two runs: a run with fewer snapshots or robots leaves the
    earlier run's later ``map_*.yaml`` files and ``robotN/`` folders, and nothing tells them apart.
    """
    from mapd.errors import MapFileError

    if out.exists() and not out.is_dir():
        raise MapFileError(f"{out}: -o must be a folder, and this is a file")
    if not out.is_dir():
        return  # a new folder: made when the first snapshot is written
    try:
        held = sorted(
            e.name
            for e in out.iterdir()
            if e.name == "poses.yaml" or (_REPLAY_DIR.fullmatch(e.name) is not None and e.is_dir())
        )
    except OSError as exc:
        raise MapFileError(f"{out}: cannot read the output folder: {exc.strerror}") from None
    if held:
        shown = ", ".join(held[:3]) + (", ..." if len(held) > 3 else "")
        raise MapFileError(
            f"{out}: already holds a replay ({shown}); give another -o folder, or remove this one first"
        )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="replay a CARMEN log through the mapper into map_server snapshots",
        description=(
            "Replay a CARMEN log with corrected poses (FLASER lines, gzip or plain) through mapd's "
            "log-odds mapper and write the growing map snapshots each robot would have sent, as "
            "map_server files DIR/robot<i>/map_<version>.yaml. Each robot's map is in its own frame "
            "(its first laser pose); DIR/poses.yaml gives those frames in the log's world frame. "
            "A log that ends early (a gzip log cut short or damaged part-way) is replayed up to "
            "there, with one warning, and the exit status is 0."
        ),
    )
    p.add_argument("log", type=Path, help="CARMEN log (.log or .log.gz)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    p.add_argument("--every", type=int, default=10, help="a snapshot every N scans (default 10)")
    p.add_argument("--resolution", type=_resolution, default=0.05, help="meters per cell (default 0.05)")
    p.add_argument(
        "--max-range",
        type=float_arg(0.01, MAX_RANGE_M),
        default=None,
        help=f"usable range in m, 0.01 to {MAX_RANGE_M:g}; longer beams only clear (default: all)",
    )
    p.add_argument("--robots", type=int, default=1, help="split the log into K overlapping parts (default 1)")
    p.add_argument(
        "--overlap", type=float, default=0.2, help="share of the log neighbouring parts share (default 0.2)"
    )
    p.set_defaults(func=cmd_replay)


def cmd_replay(args: argparse.Namespace) -> int:
    import yaml
    from tqdm import tqdm

    from mapd.errors import ConfigError, MapFileError, SourceError
    from mapd.files import atomic_write_bytes
    from mapd.grid.save import save_map
    from mapd.mapping import carmen
    from mapd.mapping.replay import first_pose, no_scan_lines, replay_log, split_range

    if args.every < 1:
        raise ConfigError("--every must be at least 1")
    if not 1 <= args.robots <= 64:
        raise ConfigError("--robots must lie in 1..64")
    if not 0.0 <= args.overlap < 1.0:
        raise ConfigError("--overlap must lie in [0, 1)")
    _check_output(args.output)
    total = carmen.count_scans(args.log)
    if total == 0:
        # SourceError, as for a log that cannot be opened: the log is the input at fault.
        raise SourceError(no_scan_lines(args.log))
    # One record of bad lines for every robot's pass: each kind of fault is said once, not per robot.
    stats = carmen.LogStats()
    poses: dict[str, list[float]] = {}
    for i in range(args.robots):
        name = f"robot{i}"
        part = split_range(total, args.robots, i, args.overlap)
        out = args.output / name
        last = None
        with tqdm(total=len(part), desc=name, unit="scan", file=sys.stderr, leave=False, disable=None) as bar:
            done = 0
            for _stamp, grid in replay_log(
                args.log,
                every=args.every,
                resolution=args.resolution,
                max_range=args.max_range,
                robots=args.robots,
                index=i,
                overlap=args.overlap,
                robot=name,
                stats=stats,
            ):
                save_map(grid, out / f"map_{grid.version:04d}.yaml")
                step = min(args.every, len(part) - done)
                bar.update(step)
                done += step
                last = grid
        pose = first_pose(args.log, robots=args.robots, index=i, overlap=args.overlap)
        if last is None or pose is None:
            print(f"{name}: no scans in its part of {args.log}", file=sys.stderr)
            continue
        poses[name] = [float(v) for v in pose]
        print(
            f"{name}: scans {part.start}..{part.stop - 1}, {last.version} snapshots, final map "
            f"{last.width} x {last.height} cells -> {out}/",
            file=sys.stderr,
        )
    if not poses:
        # Scan lines, but not one usable: a run that wrote nothing must not exit 0. One robot
        # without scans among others that had some stays the warning above.
        why = f"; the last: {stats.last_error}" if stats.last_error else ""
        raise SourceError(f"{args.log}: no usable scan in its {total} scan lines (all skipped{why})")
    try:
        args.output.mkdir(parents=True, exist_ok=True)
        text = (
            "# each robot's map frame (its first laser pose) in the log's world frame: [x m, y m, yaw rad]\n"
        )
        # Atomic: a full disk leaves the previous poses.yaml whole, never truncated.
        atomic_write_bytes(
            args.output / "poses.yaml",
            (text + yaml.safe_dump(poses, sort_keys=True, default_flow_style=None)).encode("utf-8"),
        )
    except OSError as exc:
        raise MapFileError(f"{args.output}/poses.yaml: cannot write: {exc.strerror}") from None
    return 0
