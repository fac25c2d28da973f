"""Reading CARMEN laser logs (``FLASER`` and ``ROBOTLASER1`` lines), gzip or plain, one scan at a time.

The logs in ``../shared/data/logs`` hold SLAM-corrected laser poses in ``FLASER`` lines::

    FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta ipc_timestamp ipc_hostname logger_timestamp

A ``FLASER`` line carries no angles: CARMEN's front laser covers ``fov_deg`` (180 degrees) starting at
``theta - fov/2``; 180 or 360 beams give 1 or 0.5 degree steps, 181 or 361 beams include both ends.

Bad lines never stop a replay. A line with the wrong number of fields, a non-number, a NaN or a
negative range, a pose more than :data:`MAX_COORD_M` from the origin, or a message type CARMEN does
not define is skipped, counted in :class:`LogStats`, and logged once per kind of fault with the file
and line number. Other CARMEN messages (``ODOM``, ``PARAM``, ...) are
ignored and counted separately. A log that cannot be opened or read is one :class:`SourceError`.

A log that ends early (a gzip stream cut short because the robot lost power while logging or a copy
was interrupted, a damaged stream, a failed read) is read up to there: the scans before the cut are
good data. The cut is said once, as a warning with its line and how many bytes of the file were read,
and kept in :attr:`LogStats.cut`. Only a log with no scan before the cut is a :class:`CutLogError`.

A gzip log that inflates to more than :data:`MAX_GZIP_RATIO` times its size, or to more lines than
:data:`MAX_GZIP_LINES_PER_BYTE` per byte of it (a decompression bomb: a small file of newlines), is
one :class:`LimitError`, raised while it is read, as soon as a limit is passed.
"""

from __future__ import annotations

import gzip
import logging
import math
import os
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, cast

import numpy as np

from mapd.errors import LimitError, SourceError
from mapd.files.reading import NotRegularFileError, open_regular
from mapd.grid import Pose2D

log = logging.getLogger(__name__)

#: Longest line read; anything longer is skipped, so a corrupt log cannot make us allocate without bound.
MAX_LINE_BYTES = 1 << 20
#: Most bytes a gzip log may inflate to, as a multiple of its size on disk. Real CARMEN logs inflate
#: about 4-5x (intel-corrected.log.gz 3.9x, freiburg-079-corrected.log.gz 4.6x); the most a real
#: run could write, a simulated noiseless laser standing still (the same ranges on every line, only
#: the times moving), 80x with 180 beams, 105x with 361, 130x with 1081. Deflate reaches 1000x on a
#: file of newlines: a 200 KB log of them inflated to 200 MiB, read in full on every pass (``mapd
#: replay`` makes one per robot, plus a count), and kept ``mapd replay`` busy for minutes.
MAX_GZIP_RATIO = 250
#: Most lines a gzip log may hold, per byte of its size on disk. Each line costs a Python step
#: (0.4 to 1 us), whatever its length: held to 100x alone, the 200 KB log of newlines was still read
#: for 8 s (``mapd replay``) to 17 s (the laserlog source) before its refusal. Real logs hold 0.04
#: (intel) and 0.01 (freiburg) lines per byte; a robot logging the same odometry while it stands
#: still, 0.2.
MAX_GZIP_LINES_PER_BYTE = 2
#: A gzip log may always inflate to this many bytes and lines, whatever its ratios: a small log of a
#: few scans (test data, identical lines) compresses far beyond a real one and is cheap to read.
MIN_GZIP_LIMIT_BYTES = 4 << 20
MIN_GZIP_LIMIT_LINES = 1 << 16
#: Most beams accepted in one scan.
MAX_BEAMS = 8192
#: Largest pose coordinate accepted (m). Beyond it, frame arithmetic on two poses can overflow to
#: infinity; no building is a thousand kilometres across.
MAX_COORD_M = 1e6
#: Largest timestamp accepted (s, either sign), some 300 million years. Far beyond it the time
#: between two scans overflowed to infinity (1e308 after -1e308), and a replay paced by it slept for
#: ever (NaN); below it such sums keep to a second.
MAX_STAMP_S = 1e16

# Message types CARMEN logs define that carry no front-laser scan for the mapper.
_IGNORED = frozenset(
    {
        "PARAM", "SYNC", "ODOM", "RLASER", "TRUEPOS", "NEFF", "RAWLASER1", "RAWLASER2", "RAWLASER3",
        "RAWLASER4", "ROBOTLASER2", "GPSNMEA", "GPSNMEA-GGA", "GPSNMEA-RMC", "SONAR", "BUMPER",
        "SCANMARK", "POSITIONLASER", "IMU", "VECTORMOVE", "ROBOTVELOCITY", "FOLLOWTRAJECTORY",
        "BASEVELOCITY", "ARM", "PANTILT_SCANMARK", "PANTILT_LASERPOS", "RFID", "NMEA", "REARLASER",
        "LASER1", "LASER2", "LASER3", "LASER4", "RAWLASER", "FLASER_RAW", "RLASER_RAW",
    }
)  # fmt: skip


@dataclass(frozen=True)
class LaserScan:
    """One scan: ranges in meters, beam angles relative to the laser, the laser's pose, log time."""

    ranges: np.ndarray
    angles: np.ndarray
    pose: Pose2D
    stamp: float
    line: int
    #: Ordinal of the line among the log's scan lines (bad ones included), as :func:`count_scans` counts.
    index: int = 0


@dataclass
class LogStats:
    """What a pass over a log met: scans read, bad lines skipped, other messages ignored."""

    scans: int = 0
    skipped: int = 0
    ignored: int = 0
    last_error: str = ""
    by_reason: dict[str, int] = field(default_factory=dict)
    #: Count, but log nothing: for a pass whose faults another pass over the same lines reports.
    quiet: bool = False
    #: Where and why the log ended early (the warning said), or "" if it was read to its end.
    cut: str = ""

    def skip(self, where: str, reason: str, key: str | None = None) -> None:
        """Count a skipped line; log it if it is the first of its ``key`` (default: ``reason``)."""
        self.skipped += 1
        k = reason if key is None else key
        self.by_reason[k] = self.by_reason.get(k, 0) + 1
        self.last_error = f"{where}: {reason}"
        # One warning per kind of fault keeps a log full of the same fault readable. Reasons that
        # quote the line (a message type, a count) pass a fixed key, or a file of garbage would
        # log one warning per distinct word.
        if self.by_reason[k] == 1 and not self.quiet:
            log.warning("%s: %s (skipped; further lines like it are counted, not logged)", where, reason)


class CutLogError(SourceError):
    """The log ends early at ``line``, the first line not read whole: its gzip stream is cut short
    or damaged there, or a read failed. The lines before it were good; readers stop there."""

    def __init__(self, path: Path, line: int, why: str) -> None:
        super().__init__(f"{path}: line {line}: log is corrupt or truncated {why}")
        self.path, self.line, self.why = path, line, why


class BadLine(ValueError):
    """A line that cannot be a scan; the message says why, ``key`` names the kind of fault."""

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


def _open(path: Path) -> tuple[BinaryIO, BinaryIO, int | None]:
    """The log's lines to read (inflated if gzip), the file under them (for how far it got), and a
    gzip log's size on disk (None for a plain log, whose lines are as many as its bytes allow)."""
    try:
        raw = open_regular(path)  # a FIFO without a writer blocked for ever, and /dev/zero never ended
    except FileNotFoundError:
        raise SourceError(f"{path}: no such log file") from None
    except NotRegularFileError:
        raise SourceError(f"{path}: not a regular file") from None
    except OSError as exc:
        raise SourceError(f"{path}: cannot open log: {exc.strerror or exc}") from None
    try:
        magic = raw.read(2)
        raw.seek(0)
        size = os.fstat(raw.fileno()).st_size
    except OSError as exc:
        raw.close()
        raise SourceError(f"{path}: cannot read log: {exc.strerror or exc}") from None
    if magic == b"\x1f\x8b":
        return cast(BinaryIO, gzip.GzipFile(fileobj=raw, mode="rb")), raw, size
    return raw, raw, None


def _cut(path: Path, raw: BinaryIO, line: int, exc: BaseException) -> CutLogError:
    """The error for a read that failed at ``line``, saying how far into the file it got."""
    try:
        where = f"after {raw.tell()} of {os.fstat(raw.fileno()).st_size} bytes "
    except (OSError, ValueError):
        where = ""
    return CutLogError(path, line, f"{where}({exc})")


def _bomb(path: Path, by_bytes: bool, max_bytes: int, max_lines: int) -> LimitError:
    """The error for a gzip log past its limit of inflated bytes (``by_bytes``) or of lines."""
    if by_bytes:
        what = f"inflates to more than {max_bytes} bytes, over {MAX_GZIP_RATIO} times its size on disk"
        real = "a CARMEN log inflates about 5 times"
    else:
        what = (
            f"holds more than {max_lines} lines, over {MAX_GZIP_LINES_PER_BYTE} per byte of its size on disk"
        )
        real = "a CARMEN log holds under 1 per 25 bytes"
    return LimitError(f"{path}: gzip log {what} ({real}): refused as a decompression bomb")


def _lines(path: Path) -> Iterator[tuple[int, bytes]]:
    """(line number, line) pairs; overlong lines come back as b'' plus a sentinel of their own.

    Raises :class:`CutLogError` where the log stops being readable, after the lines before it, and
    :class:`LimitError` as soon as a gzip log has inflated to more bytes or lines than its size
    allows (:data:`MAX_GZIP_RATIO`, :data:`MAX_GZIP_LINES_PER_BYTE`), before the rest is inflated.
    """
    fh, raw, packed = _open(path)
    # A gzip log is held to limits in proportion to its size, counted as its lines are inflated, so
    # a decompression bomb stops there, not after inflating all of itself (once per pass).
    max_bytes = max_lines = sys.maxsize
    if packed is not None:
        max_bytes = max(MIN_GZIP_LIMIT_BYTES, MAX_GZIP_RATIO * packed)
        max_lines = max(MIN_GZIP_LIMIT_LINES, MAX_GZIP_LINES_PER_BYTE * packed)
    inflated = 0
    try:
        number = 0
        while True:
            try:
                chunk = fh.readline(MAX_LINE_BYTES)
            except (OSError, EOFError, zlib.error) as exc:
                raise _cut(path, raw, number + 1, exc) from None
            if not chunk:
                return
            number += 1
            inflated += len(chunk)
            if inflated > max_bytes or number > max_lines:
                raise _bomb(path, inflated > max_bytes, max_bytes, max_lines)
            if len(chunk) >= MAX_LINE_BYTES and not chunk.endswith(b"\n"):
                # Drain the rest of the overlong line so the next line is read whole.
                while True:
                    try:
                        more = fh.readline(MAX_LINE_BYTES)
                    except (OSError, EOFError, zlib.error) as exc:
                        raise _cut(path, raw, number, exc) from None
                    inflated += len(more)
                    if inflated > max_bytes:
                        raise _bomb(path, True, max_bytes, max_lines)
                    if not more or more.endswith(b"\n"):
                        break
                yield number, b"\x00overlong"
                continue
            yield number, chunk
    finally:
        fh.close()
        raw.close()


def _floats(tokens: list[str], what: str) -> np.ndarray:
    try:
        return np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise BadLine(f"{what} holds a value that is not a number") from None


def _check_ranges(ranges: np.ndarray) -> None:
    if np.isnan(ranges).any():
        raise BadLine("NaN range")
    if (ranges < 0).any():
        raise BadLine("negative range")


def _check_pose(x: float, y: float, stamp: float) -> None:
    if abs(x) > MAX_COORD_M or abs(y) > MAX_COORD_M:
        raise BadLine(f"pose is more than {MAX_COORD_M:g} m from the origin")
    if abs(stamp) > MAX_STAMP_S:
        raise BadLine(f"timestamp {stamp:.3g} is beyond {MAX_STAMP_S:g} s")


def _beam_angles(n: int, fov: float) -> np.ndarray:
    # 181/361 beams include both ends of the field of view; 180/360 beams step fov/n from the start.
    step = fov / (n - 1) if (n % 2 == 1 and n > 1) else fov / n
    return -fov / 2.0 + step * np.arange(n, dtype=np.float64)


def parse_flaser(tokens: list[str], fov: float, line: int) -> LaserScan:
    """A ``FLASER`` line split on whitespace; raises :class:`BadLine`."""
    if len(tokens) < 2:
        raise BadLine("FLASER line has no beam count")
    try:
        n = int(tokens[1])
    except ValueError:
        raise BadLine(f"FLASER beam count {tokens[1][:40]!r} is not an integer", "FLASER count") from None
    if not 1 <= n <= MAX_BEAMS:
        raise BadLine(f"FLASER beam count {n} is outside 1..{MAX_BEAMS}", "FLASER count")
    expected = 2 + n + 6 + 3
    if len(tokens) != expected:
        raise BadLine(f"FLASER with {n} beams needs {expected} fields, got {len(tokens)}", "FLASER fields")
    ranges = _floats(tokens[2 : 2 + n], "ranges")
    _check_ranges(ranges)
    tail = _floats([*tokens[2 + n : 2 + n + 3], tokens[2 + n + 6]], "pose or timestamp")
    if not np.isfinite(tail).all():
        raise BadLine("pose or timestamp is not finite")
    x, y, theta, stamp = (float(v) for v in tail)
    _check_pose(x, y, stamp)
    return LaserScan(ranges, _beam_angles(n, fov), Pose2D(x, y, theta), stamp, line)


def parse_robotlaser1(tokens: list[str], line: int) -> LaserScan:
    """A ``ROBOTLASER1`` line (angles and laser pose given in the line); raises :class:`BadLine`."""
    # ROBOTLASER1 type start fov res maxrange accuracy remission_mode n r_1..r_n m v_1..v_m
    #   laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd side turn ts host logger_ts
    if len(tokens) < 9:
        raise BadLine("ROBOTLASER1 line is too short")
    try:
        n = int(tokens[8])
        if not 1 <= n <= MAX_BEAMS:
            raise BadLine(f"ROBOTLASER1 beam count {n} is outside 1..{MAX_BEAMS}", "ROBOTLASER1 count")
        m = int(tokens[9 + n]) if len(tokens) > 9 + n else -1
    except ValueError:
        raise BadLine("ROBOTLASER1 beam or remission count is not an integer") from None
    if not 0 <= m <= MAX_BEAMS:
        raise BadLine("ROBOTLASER1 remission count is missing or out of range")
    expected = 10 + n + m + 14
    if len(tokens) != expected:
        raise BadLine(
            f"ROBOTLASER1 with {n} beams and {m} remissions needs {expected} fields, got {len(tokens)}",
            "ROBOTLASER1 fields",
        )
    head = _floats(tokens[2:4], "start angle or field of view")
    ranges = _floats(tokens[9 : 9 + n], "ranges")
    _check_ranges(ranges)
    base = 10 + n + m
    tail = _floats([*tokens[base : base + 3], tokens[base + 11]], "pose or timestamp")
    if not (np.isfinite(tail).all() and np.isfinite(head).all()):
        raise BadLine("angles, pose or timestamp are not finite")
    start, fov = float(head[0]), float(head[1])
    step = fov / (n - 1) if n > 1 else 0.0
    angles = start + step * np.arange(n, dtype=np.float64)
    x, y, theta, stamp = (float(v) for v in tail)
    _check_pose(x, y, stamp)
    return LaserScan(ranges, angles, Pose2D(x, y, theta), stamp, line)


def read_scans(
    path: str | os.PathLike[str], *, stats: LogStats | None = None, fov_deg: float = 180.0
) -> Iterator[LaserScan]:
    """Yield every scan of a CARMEN log in order; bad lines are skipped and counted in ``stats``.

    A log that ends early ends the scans there: the cut is warned of once per ``stats`` and kept in
    its ``cut``; a log with no scan before the cut raises :class:`CutLogError`.
    """
    p = Path(path)
    st = stats if stats is not None else LogStats()
    fov = math.radians(fov_deg)
    ordinal = -1
    read = 0  # scans of this pass, not of ``st``, which other passes may share
    try:
        for number, raw in _lines(p):
            if raw.startswith((b"FLASER ", b"ROBOTLASER1 ")):
                ordinal += 1
            scan = _scan(p, number, raw, fov, st)
            if scan is None:
                continue
            st.scans += 1
            read += 1
            yield LaserScan(scan.ranges, scan.angles, scan.pose, scan.stamp, number, ordinal)
    except CutLogError as exc:
        if read == 0:
            raise  # nothing usable before the damage: the log is refused, as one it cannot open
        _log_cut(st, exc, read)


def _scan(p: Path, number: int, raw: bytes, fov: float, st: LogStats) -> LaserScan | None:
    """Line ``number`` as a scan, or None: not one (counted in ``st`` if a bad line)."""
    where = f"{p}: line {number}"
    if raw == b"\x00overlong":
        st.skip(where, f"line longer than {MAX_LINE_BYTES} bytes")
        return None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        st.skip(where, "line is not ASCII text")
        return None
    tokens = text.split()
    if not tokens or tokens[0].startswith("#"):
        return None
    kind = tokens[0]
    try:
        if kind == "FLASER":
            return parse_flaser(tokens, fov, number)
        if kind == "ROBOTLASER1":
            return parse_robotlaser1(tokens, number)
        if kind in _IGNORED:
            st.ignored += 1
            return None
        raise BadLine(f"unknown message type {kind[:40]!r}", "unknown message type")
    except BadLine as exc:
        st.skip(where, str(exc), exc.key)
        return None


def _log_cut(stats: LogStats, cut: CutLogError, scans: int) -> None:
    """Record that the log ends early at ``cut`` after ``scans`` scans; warn the first time for ``stats``.

    Every pass over the log meets the same cut (``mapd replay`` reads it once per robot): one
    warning for the run, not one per pass.
    """
    if stats.cut:
        return
    stats.cut = stats.last_error = (
        f"{cut.path}: line {cut.line}: log ends early: corrupt or truncated {cut.why}; "
        f"read up to there ({scans} scans)"
    )
    if not stats.quiet:
        log.warning("%s", stats.cut)


def count_scans(path: str | os.PathLike[str]) -> int:
    """How many lines of the log look like scans (a cheap first pass, used to split a log among robots).

    Lines after a cut are not there to count; the pass that reads the scans says where the log ends.
    A cut before the first scan line raises :class:`CutLogError`.
    """
    n = 0
    try:
        for _number, raw in _lines(Path(path)):
            if raw.startswith((b"FLASER ", b"ROBOTLASER1 ")):
                n += 1
    except CutLogError:
        if n == 0:
            raise
    return n
