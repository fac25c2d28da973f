"""``mapd train``: train the paper codec's networks on map tiles and write a model folder."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mapd.bench.common import MAX_SEED, int_arg

#: Most scans of one simulated run: 20,000 sim seconds at 5 Hz, about 70 times the default.
MAX_SIM_SCANS = 100_000

EPILOG = """\
example (the shipped model):
  mapd train --maps ../shared/data/maps --epochs 200 --tile 64 --seed 0 --levels 16 \\
    --tiles-per-epoch 3072 --batch 16 --lr 0.002 --val-fraction 0.2 --val-tiles 256 \\
    --device cpu --threads 1 -o models/paper-v3

The folder gets weights.npz, model.json (settings, split, metrics, sha256) and MODEL_CARD.md.
Use it with [codec.paper] model = "NAME" (and model_dir = "DIR" when it is not under models/).

maps in the making (snapshots every 100 scans of a log and of simulated buildings, cached):
  mapd train --snapshots-log ../shared/data/logs/freiburg-079-corrected.log.gz --snapshots-sim 1 2 3 4 \\
    --exclude-place intel --epochs 20 --tile 64 --tiles-per-epoch 3072 -o /tmp/both
  (add --no-finished to train on the snapshots only; score with python -m mapd.train.heldout)
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train the paper codec (CNN_feature + CNN_recovery) on map tiles",
        description="Train the paper codec's networks end to end through the quantizer on tiles of "
        "real maps, validate on whole held-out maps (split by place), and write a model folder.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--maps", type=Path, default=None, help="folder of map_server maps (default: the shared data)"
    )
    # --epochs to --threads: mapd.train.settings.check_settings bounds them, one line before any work.
    p.add_argument("--epochs", type=int, default=12, help="passes over --tiles-per-epoch tiles (default 12)")
    p.add_argument(
        "--tile", type=int, default=64, help="tile side in cells, a multiple of 4 from 8 to 256 (default 64)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of weights and tile sampler (default 0)")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="model folder to write, e.g. models/NAME (new, or a model folder it replaces whole)",
    )
    p.add_argument("--levels", type=int, default=16, help="quantizer levels of m_feature (default 16)")
    p.add_argument("--tiles-per-epoch", type=int, default=2048, help="tiles drawn per epoch (default 2048)")
    p.add_argument("--batch", type=int, default=16, help="tiles per step (default 16)")
    p.add_argument("--lr", type=float, default=2e-3, help="Adam learning rate, in (0, 1] (default 2e-3)")
    p.add_argument(
        "--edge-weight",
        type=float,
        default=1.0,
        help="loss weight of cells on a class boundary, others 1 (default 1: the paper's plain MSE)",
    )
    p.add_argument("--val-fraction", type=float, default=0.2, help="share of places held out (default 0.2)")
    p.add_argument(
        "--val-tiles", type=int, default=256, help="held-out tiles scored each epoch (default 256)"
    )
    p.add_argument("--device", default="auto", help="auto (CUDA when available), cpu or cuda")
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch CPU threads, 0 to 256 (default 0: torch's default); CPU weights are reproducible for one count",
    )
    snap = p.add_argument_group("maps in the making (snapshots, as a Gmapping run saves them)")
    snap.add_argument(
        "--snapshots-log",
        type=Path,
        nargs="+",
        default=[],
        metavar="LOG",
        help="CARMEN logs (corrected poses) replayed through mapd's mapper; their snapshots train too",
    )
    snap.add_argument(
        "--snapshots-sim",
        type=int_arg(0, MAX_SEED),
        nargs="+",
        default=[],
        metavar="SEED",
        help="simulated buildings (worldgen seeds) mapped by one robot; their snapshots train too",
    )
    snap.add_argument(
        "--snapshot-every", type=int, default=100, metavar="N", help="scans between snapshots (default 100)"
    )
    snap.add_argument(
        "--sim-scans",
        type=int_arg(1, MAX_SIM_SCANS),
        default=1500,
        metavar="N",
        help=f"scans per simulated run, 1 to {MAX_SIM_SCANS} (default 1500)",
    )
    snap.add_argument(
        "--no-finished",
        action="store_true",
        help="train on the snapshots only (finished maps still validate)",
    )
    snap.add_argument(
        "--exclude-place",
        nargs="+",
        default=[],
        metavar="PLACE",
        help="places (split groups, e.g. intel) left out of training and validation, e.g. a held-out log's",
    )
    snap.add_argument(
        "--cache", type=Path, default=None, help="snapshot cache (default $MAPD_CACHE or ~/.cache/mapd)"
    )
    stop = p.add_argument_group(
        "stopping and going on (the state after each epoch is kept in OUTPUT.checkpoint)"
    )
    stop.add_argument(
        "--resume",
        action="store_true",
        help="go on from OUTPUT.checkpoint (same settings): the same weights as a run that never stopped",
    )
    stop.add_argument(
        "--time-limit",
        type=float,
        default=0.0,
        metavar="S",
        help="stop after the epoch that ends S seconds in, keeping the checkpoint; exit status 3 (default 0: none)",
    )
    p.add_argument("--no-eval", action="store_true", help="skip the whole-map evaluation at the end")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)


def _command(args: argparse.Namespace, maps: Path) -> list[str]:
    """The command line that reproduces this run, every setting spelled out."""
    return [
        "mapd", "train", "--maps", str(maps), "--epochs", str(args.epochs), "--tile", str(args.tile),
        "--seed", str(args.seed), "--levels", str(args.levels),
        "--tiles-per-epoch", str(args.tiles_per_epoch), "--batch", str(args.batch), "--lr", str(args.lr),
        *(["--edge-weight", str(args.edge_weight)] if args.edge_weight != 1.0 else []),
        "--val-fraction", str(args.val_fraction), "--val-tiles", str(args.val_tiles),
        "--device", args.device, *(["--threads", str(args.threads)] if args.threads else []),
        *_snapshot_args(args),
        "-o", str(args.output),
    ]  # fmt: skip


def _snapshot_args(args: argparse.Namespace) -> list[str]:
    out: list[str] = []
    if args.snapshots_log:
        out += ["--snapshots-log", *map(str, args.snapshots_log)]
    if args.snapshots_sim:
        out += ["--snapshots-sim", *map(str, args.snapshots_sim)]
    if args.snapshots_log or args.snapshots_sim:
        out += ["--snapshot-every", str(args.snapshot_every)]
        if args.snapshots_sim:
            out += ["--sim-scans", str(args.sim_scans)]
    if args.no_finished:
        out.append("--no-finished")
    if args.exclude_place:
        out += ["--exclude-place", *args.exclude_place]
    return out


def cmd_train(args: argparse.Namespace) -> int:
    from mapd.data import data_dir
    from mapd.errors import ConfigError
    from mapd.train.checkpoint import TrainingPaused
    from mapd.train.loop import main_train
    from mapd.train.settings import TrainConfig
    from mapd.train.snapshots import SnapshotSpec

    maps = args.maps
    if maps is None:
        base = data_dir()
        if base is None:
            raise ConfigError("no --maps given and no shared data found (set MAPD_DATA)")
        maps = base / "maps"
    if not maps.is_dir():
        raise ConfigError(f"--maps {maps}: not a folder")
    cfg = TrainConfig(
        maps=maps,
        out=args.output,
        epochs=args.epochs,
        tile=args.tile,
        seed=args.seed,
        levels=args.levels,
        tiles_per_epoch=args.tiles_per_epoch,
        batch=args.batch,
        lr=args.lr,
        edge_weight=args.edge_weight,
        val_fraction=args.val_fraction,
        val_tiles=args.val_tiles,
        device=args.device,
        threads=args.threads,
        progress=not args.quiet,
        evaluate=not args.no_eval,
        snapshots=SnapshotSpec(
            logs=tuple(args.snapshots_log),
            sims=tuple(args.snapshots_sim),
            every=args.snapshot_every,
            sim_scans=args.sim_scans,
            cache=args.cache,
        ),
        finished=not args.no_finished,
        exclude_places=tuple(args.exclude_place),
        resume=args.resume,
        time_limit=args.time_limit,
        extra={"argv": _command(args, maps)},
    )
    try:
        meta = main_train(cfg)
    except TrainingPaused as paused:
        print(f"mapd: {paused}", file=sys.stderr)
        return 3
    out = f"{args.output}: weights sha256 {meta['weights_sha256'][:12]}, {meta['parameters']} parameters"
    m = meta.get("metrics", {}).get("validation")
    if m:
        out += (
            f"; validation ({m['maps']} maps): ratio {m['ratio']:.1f}:1, PSNR {m['psnr_mean']:.2f} dB,"
            f" SSIM {m['ssim_mean']:.4f}"
        )
    print(out)
    return 0
