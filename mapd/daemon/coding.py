"""Own maps into signed envelopes, and the daemon's CSV logs: the work that runs off the event loop.

:class:`Coder` encodes a version (against a base or whole), wraps it in an envelope with the next
sequence number, signs it, measures it (and its quality, for lossy codecs when asked), and appends
a row to ``updates.csv``. It is called from worker threads only (the publisher's encode jobs and
keyframe queries), possibly two at once, so its shared bits are locked.

:class:`CsvLog` appends rows to a CSV file (from worker threads; the loop never waits on the disk).
"""

from __future__ import annotations

import csv
import threading
import time
from pathlib import Path
from typing import Any

from mapd.codec import decode, encode, read_header
from mapd.codec.base import CodecOptions
from mapd.codec.metrics import psnr, ssim
from mapd.daemon.state import StateStore
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import Identity


class CsvLog:
    """Rows appended to one CSV file, header first. Blocking and thread-safe: call it off the loop."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()

    def write(self, rows: list[dict[str, Any]]) -> None:
        if not rows:
            return
        with self._lock, open(self.path, "a", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            if fh.tell() == 0:
                w.writeheader()
            w.writerows(rows)


class Coder:
    """Encodes own versions into envelopes. Thread-safe; CPU-heavy: never call it on the loop."""

    def __init__(
        self,
        *,
        robot: str,
        fleet: str,
        codec: str,
        options: CodecOptions | None,
        lossless: bool,
        measure_quality: bool,
        identity: Identity | None,
        max_cells: int,
        store: StateStore,
        log: CsvLog,
    ) -> None:
        self.robot = robot
        self.fleet = fleet
        self.codec = codec
        self.options = options
        self.lossless = lossless
        self.measure_quality = measure_quality
        self.identity = identity
        self.max_cells = max_cells
        self.store = store
        self.log = log
        self._lock = threading.Lock()
        self.stats: dict[str, Any] = {"name": codec}
        #: This robot's map frame in the fleet frame, when its source knows it (sent in every envelope).
        self.frame_pose: Pose2D | None = None

    def envelope(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Envelope:
        """``grid`` coded against ``base`` (None: whole), wrapped, signed, logged."""
        t0 = time.perf_counter()
        payload = encode(grid, self.codec, base, options=self.options)
        enc_ms = 1000 * (time.perf_counter() - t0)
        head = read_header(payload, max_cells=self.max_cells)
        env = Envelope(
            fleet=self.fleet,
            robot=self.robot,
            version=grid.version,
            base_version=head.base_version if head.delta else 0,
            codec=self.codec,
            variant=head.variant,
            width=grid.width,
            height=grid.height,
            resolution=grid.resolution,
            origin=grid.origin,
            frame_id=grid.frame_id,
            stamp=grid.stamp,
            seq=self.store.next_seq(),
            payload=payload,
            frame_pose=self.frame_pose,
        )
        if self.identity is not None:
            env = env.signed(self.identity)
        row: dict[str, Any] = {
            "time": round(time.time(), 3),
            "version": grid.version,
            "kind": "delta" if head.delta else "keyframe",
            "cells": grid.cells,
            "bytes": len(payload),
            "ratio": round(grid.cells / len(payload), 2),
            "encode_ms": round(enc_ms, 2),
            "psnr": "",
            "ssim": "",
        }
        if self.measure_quality and not self.lossless:
            back = decode(payload, base, max_cells=self.max_cells, options=self.options)
            row["psnr"], row["ssim"] = (
                round(psnr(grid.data, back.data), 3),
                round(ssim(grid.data, back.data), 5),
            )
        with self._lock:
            self.stats = {
                **self.stats,
                "last_version": grid.version,
                "last_bytes": len(payload),
                "last_ratio": row["ratio"],
                "last_encode_ms": row["encode_ms"],
                "last_kind": row["kind"],
            }
        self.log.write([row])
        return env
