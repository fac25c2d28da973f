"""Own maps into signed envelopes, and the daemon's CSV logs: the work that runs off the event loop.

:class:`Coder` encodes a version (against a base or whole), wraps it in an envelope with the next
sequence number, signs it, measures it (and its quality, for lossy codecs when asked), and appends
a row to ``updates.csv``. It is called from worker threads only (the publisher's encode jobs and
keyframe queries), possibly two at once, so its shared bits are locked.

:class:`CsvLog` appends rows to a CSV file (from worker threads; the loop never waits on the disk).
"""

from __future__ import annotations

import contextlib
import csv
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from mapd.codec import decode, encode, read_header
from mapd.codec.base import CodecOptions
from mapd.codec.metrics import psnr, ssim
from mapd.daemon.state import StateStore
from mapd.envelope import Envelope
from mapd.files.folders import Folder
from mapd.files.outage import WriteOutage
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import Identity

log = logging.getLogger(__name__)


class CsvLog:
    """Rows appended to one CSV file, header first. Blocking and thread-safe: call it off the loop.

    A log is not state: a row that cannot be written (a full disk) is dropped with one log line (one
    per run of failures, not one per row), and never stops what logged it (coding a map). The first
    write of a run cuts a torn last line (power lost mid-append) back to the last whole row, so the
    next row never runs into half of an old one. Past ``max_bytes`` the file moves to
    ``<name>.1.csv`` (replacing the one before) and a new one starts, header first: a base station
    of 16 robots may write ``fused.csv`` rows at up to ~8 a second (a row per robot per global
    map), which would fill a robot's disk over months.
    """

    #: Bytes a log grows to before it rotates (two files at most: this and ``<name>.1.csv``).
    MAX_BYTES = 16 << 20

    def __init__(self, path: Path, max_bytes: int = MAX_BYTES) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self._checked = False
        self._outage = WriteOutage(log)
        #: The log's folder, and the disk it was on at the first write: once that disk is
        #: unmounted, an append would go into the folder left under it, where nobody looks.
        self._folder = Folder(path.parent)

    def write(self, rows: list[dict[str, Any]]) -> None:
        if not rows:
            return
        with self._lock:
            end: int | None = None  # where the file ended before this append
            if (why := self._folder.unusable()) is not None:
                self._outage.failed(f"cannot write {self.path} (rows dropped until it can): its folder {why}")
                return
            try:
                if not self._checked:
                    _cut_torn_line(self.path)
                    self._checked = True
                with contextlib.suppress(FileNotFoundError):
                    if self.path.stat().st_size >= self.max_bytes:
                        os.replace(self.path, self.path.with_suffix(".1" + self.path.suffix))
                with open(self.path, "a", newline="") as fh:
                    end = fh.tell()
                    w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                    if end == 0:
                        w.writeheader()
                    w.writerows(rows)
            except OSError as exc:
                # A full disk takes part of the rows (the room left in the file's last block): cut
                # back to the last whole row, or the next append, once there is room, runs into it
                # (a torn row in the middle of the log). Cutting needs no room; if it fails all the
                # same, the next write's first look cuts it.
                if end is not None:
                    try:
                        os.truncate(self.path, end)
                    except OSError:
                        self._checked = False
                self._outage.failed(
                    f"cannot write {self.path} (rows dropped until it can): {exc.strerror or exc}"
                )
                return
            self._outage.recovered(f"writing {self.path} again")


def _cut_torn_line(path: Path) -> None:
    """Truncate ``path`` after its last newline when it ends inside a line (a torn append)."""
    try:
        fh = open(path, "rb+")  # noqa: SIM115 - closed below; a missing file has nothing torn
    except FileNotFoundError:
        return
    with fh:
        end = fh.seek(0, os.SEEK_END)
        if end == 0:
            return
        fh.seek(end - 1)
        if fh.read(1) == b"\n":
            return
        pos = end
        while pos > 0:  # backwards a piece at a time: a row is short, the file need not be
            start = max(0, pos - 4096)
            fh.seek(start)
            piece = fh.read(pos - start)
            nl = piece.rfind(b"\n")
            if nl >= 0:
                fh.truncate(start + nl + 1)
                break
            pos = start
        else:
            fh.truncate(0)  # not even the header is whole: it is written again
        fh.flush()
        os.fsync(fh.fileno())
    log.warning("%s ended inside a row (an interrupted write); cut back to its last whole row", path)


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
