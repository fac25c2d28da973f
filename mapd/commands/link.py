"""``mapd link send | recv``: commission a UWB radio link by moving one file across it, verified.

Run ``mapd link recv --port /dev/ttyUSB0 -o got.bin`` on one robot and
``mapd link send --port /dev/ttyUSB0 map.mapd`` on the other. Both print the bytes moved, the time,
the goodput against the configured link rate, and the link statistics (resends, damaged frames,
duplicates, RTT). ``recv`` exits 0 after one complete message whose hash checked out, once the sender
has gone quiet (it answers the sender's repeats until then: ``--linger``); ``send`` exits 0 once the
receiver acknowledged it, 1 when it did not before ``--deadline`` or the receiver fell silent after
the whole file was on the air (it may have got it: its last acks may have been lost). A failed ``send``
or ``recv`` prints the same statistics (``"ok": false`` and the ``"error"`` with ``--json``) and what
the line carried, before the error: nothing at all (a dead radio, the wrong port), frames whose link
tag failed (another ``--key``), or frames the framing spoiled (another ``--baud``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from mapd.bench.common import DAY_S, UWB_MAX_BPS, float_arg, int_arg
from mapd.commands.common import check_writable
from mapd.commands.link_waits import LINGER_MAX_S, LINGER_S, PEER_TIMEOUT_S, SILENT_TIMEOUTS, Quiet, Silence
from mapd.errors import ConfigError, MapdError, TransportError
from mapd.keys import read_key_file

#: The largest frame ``[transports.uwb] max_frame`` takes.
MAX_FRAME = 4096
#: A link id on the air.
LINK_ID = int_arg(1, 254)
#: A wait in seconds: at least a tenth of a second (a frame's time), at most a day.
SECONDS = float_arg(0.1, DAY_S)
#: A goodput is reported only for a message at least this many pacer bursts long. The pacer lets its
#: first burst (two frames) out at once, unpaced; on a message not much longer than that the time
#: measures the serial port, not the link, and a 5-byte file "ran" at 4933 % of the link rate. Ten
#: bursts bound that error to about a tenth.
MEASURABLE_BURSTS = 10
#: Seconds between two progress lines on a terminal.
PROGRESS_EVERY_S = 5.0
#: Seconds between two looks at the link's counters and events while waiting (linger, silence).
POLL_S = 0.1


def _max_frame(text: str) -> int:
    """``--max-frame``, from the framing's shortest frame to :data:`MAX_FRAME`; transports is
    imported only when the option is given, as the handlers do, never at every ``mapd`` start."""
    from transports.uwb.framing import MIN_FRAME

    return int_arg(MIN_FRAME, MAX_FRAME)(text)


_SHOWN = (
    "bytes_tx",
    "bytes_rx",
    "frames_tx",
    "frames_rx",
    "resends",
    "timeouts",
    "damaged",  # damage_words: the total, and what caught them (on a keyed link, the tag)
    "bad_frames",
    "duplicates",
    "rtt_ms",
    "peak_bps_1s",
)


def _common(p: argparse.ArgumentParser, node: int) -> None:
    p.add_argument("--port", required=True, help="serial device of the UWB radio (e.g. /dev/ttyUSB0)")
    # The bounds of [transports.uwb] baud, link_rate_bps and max_frame; the pair's rule is _config's.
    p.add_argument(
        "--baud", type=int_arg(1200, 4_000_000), default=115200, help="serial baud rate (default 115200)"
    )
    p.add_argument(
        "--rate-bps",
        type=int_arg(2000, UWB_MAX_BPS),
        default=12500,
        help="link rate to pace at, bits/s (default 12500)",
    )
    p.add_argument(
        "--max-frame",
        type=_max_frame,
        default=224,
        help=f"largest frame on the wire, at most {MAX_FRAME} (default 224)",
    )
    p.add_argument("--key", type=Path, help="fleet key file (hex or raw, 16+ bytes): sign and verify frames")
    p.add_argument("--node", type=LINK_ID, default=node, help=f"this end's link id (default {node})")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "link",
        help="commission a UWB serial link: send or receive one file, with statistics",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    lsub = p.add_subparsers(dest="link_action", metavar="ACTION", title="actions")
    s = lsub.add_parser("send", help="send FILE and wait until the peer has verified it")
    s.add_argument("file", type=Path, help="file to send")
    _common(s, node=1)
    # Checked by cmd_send together with --node (a peer must not be this end): one line either way.
    s.add_argument("--peer", type=int, action="append", help="receiver link id (repeatable; default 2)")
    s.add_argument("--deadline", type=SECONDS, default=300.0, help="give up after this many seconds (300)")
    s.add_argument(
        "--peer-timeout",
        type=float_arg(1.0, 600.0),
        default=PEER_TIMEOUT_S,
        help="a receiver silent this long is down; send gives up on one silent for twice this after "
        f"the whole file was on the air (default {PEER_TIMEOUT_S:g} s, as [transports.uwb] peer_timeout_s)",
    )
    s.set_defaults(func=cmd_send)
    r = lsub.add_parser("recv", help="receive one message, verify it, write it to -o FILE")
    r.add_argument("-o", "--output", type=Path, required=True, help="file to write")
    _common(r, node=2)
    # An id no sender can have would wait out the whole --timeout for nothing.
    r.add_argument("--peer", type=LINK_ID, help="accept only from this link id (default: any)")
    r.add_argument("--timeout", type=SECONDS, default=600.0, help="give up after this many seconds (600)")
    r.add_argument(
        "--linger",
        type=float_arg(0.0, LINGER_MAX_S),
        default=LINGER_S,
        help="after the message, keep answering the sender until it has been quiet this long "
        f"(default {LINGER_S:g} s: three of its longest retransmission waits); at most {LINGER_MAX_S:g} s in all",
    )
    r.set_defaults(func=cmd_recv)
    p.set_defaults(func=lambda args: p.print_help() or 2)


def _config(args: argparse.Namespace, max_message: int) -> Any:
    from transports.uwb.arq import ArqConfig
    from transports.uwb.framing import MIN_FRAME

    if not 1 <= args.node <= 254:
        raise ConfigError(f"--node {args.node} is not a link id in 1..254")
    if args.max_frame < MIN_FRAME or args.rate_bps / 8 < 2 * args.max_frame:
        raise ConfigError(
            f"--max-frame {args.max_frame} must be >= {MIN_FRAME}, and two such frames must fit in one second of --rate-bps"
        )
    return ArqConfig(
        node_id=args.node,
        max_frame=args.max_frame,
        rate_bps=float(args.rate_bps),
        max_message_bytes=max(max_message, 1024),
        deadline_s=getattr(args, "deadline", 300.0),
        peer_timeout_s=getattr(args, "peer_timeout", PEER_TIMEOUT_S),
        key=read_key_file(args.key, "--key"),
    )


def _goodput(args: argparse.Namespace, nbytes: int, dt: float) -> tuple[str, float | None]:
    """The goodput words for the summary line, and the b/s (None when too short to measure)."""
    burst = 2 * args.max_frame  # the ARQ's pacer: a token bucket two frames deep
    if nbytes < MEASURABLE_BURSTS * burst:
        return (
            f"goodput too short to measure (under {MEASURABLE_BURSTS} pacer bursts of {burst} bytes)",
            None,
        )
    goodput = 8 * nbytes / max(dt, 1e-9)
    return (
        f"goodput {goodput:.0f} b/s ({100 * goodput / args.rate_bps:.1f} % of {args.rate_bps} b/s)",
        goodput,
    )


async def _progress(link: Any, what: str, total: int | None) -> None:
    """Every :data:`PROGRESS_EVERY_S` on a terminal, the bytes moved so far: a transfer at a few
    kb/s takes minutes, and a silent one looks hung. Off when stderr is not a terminal (logs), as
    ``mapd replay``'s progress bar is; cancelled by the caller when the transfer ends."""
    import asyncio

    if not sys.stderr.isatty():
        return
    while True:
        await asyncio.sleep(PROGRESS_EVERY_S)
        moved = int(link.stats().get(what, 0) or 0)
        # Bytes on the wire include frame headers and resends: a share of the file, not exact.
        share = f" (~{min(99.0, 100 * moved / total):.0f} % of {total})" if total else ""
        print(f"link: {moved} bytes {'sent' if what == 'bytes_tx' else 'received'}{share}", file=sys.stderr)


def _report(
    args: argparse.Namespace, summary: dict[str, Any], stats: dict[str, Any], error: MapdError | None = None
) -> None:
    """The summary line and the link line (or one JSON document); ``error``: the command failed, and
    raises it next (the CLI's one ``mapd: error:`` line on stderr): the figures are printed first
    because a failed commissioning is when they are needed, to tell a wrong key from a dead line."""
    from mapd.daemon.headline import damage_words, damaged

    if args.json:
        doc = {"ok": error is None, "error": None if error is None else str(error), **summary}
        print(json.dumps({**doc, "damaged": damaged(stats), "stats": stats}, indent=2))
        return
    print(summary["line"])
    words = damage_words(stats) or "damaged=None"
    print("link: " + "  ".join(words if k == "damaged" else f"{k}={stats.get(k)}" for k in _SHOWN))


def _heard(stats: dict[str, Any]) -> str:
    """What the line carried, for a failed command: in words that tell the usual commissioning
    faults apart, which otherwise all end in the same timeout."""
    rx = int(stats.get("bytes_rx") or 0)
    if not rx:
        return "nothing heard on the line (is the other end running, on this --port?)"
    valid = int(stats.get("frames_rx") or 0)
    words = [f"heard {rx} bytes, {valid} valid frames"]
    # A wrong baud breaks the framing itself (COBS, the length). Frames whole but for the check at
    # their end (the CRC; on a keyed link the tag, which replaces it), and none valid, point at the
    # keys: an unkeyed end finds a keyed end's frames failing the CRC.
    broken = sum(int(stats.get(k) or 0) for k in ("cobs_errors", "oversize", "runts"))
    keys = not broken and not valid
    if broken:
        words.append(f"{broken} broken (another --baud, or a noisy line?)")
    if n := int(stats.get("crc_errors") or 0):
        words.append(f"{n} failed the CRC" + (" (a --key there, and none here?)" if keys else ""))
    if n := int(stats.get("bad_signature") or 0):
        words.append(f"{n} failed the link tag" + (" (another --key?)" if keys else ""))
    if n := int(stats.get("signed_no_key") or 0):
        words.append(f"{n} signed, and no --key here")
    if n := int(stats.get("unsigned") or 0):
        words.append(f"{n} unsigned, and a --key here")
    return ", ".join(words)


def cmd_send(args: argparse.Namespace) -> int:
    import asyncio

    from mapd.files.reading import DATA_READ_TIMEOUT_S, read_capped
    from transports.uwb.options import MAX_MESSAGE

    try:
        # /dev/zero was read until memory ran out
        data = read_capped(args.file, MAX_MESSAGE, timeout_s=DATA_READ_TIMEOUT_S)
    except OSError as exc:
        raise TransportError(f"{args.file}: cannot read: {exc.strerror}") from None
    if len(data) > MAX_MESSAGE:
        raise TransportError(f"{args.file}: over the {MAX_MESSAGE} bytes one message can carry")
    peers = args.peer or [2]
    bad = [p for p in peers if not 1 <= p <= 254 or p == args.node]
    if bad:
        raise ConfigError(f"--peer {bad[0]} is not a link id in 1..254 other than --node {args.node}")
    return asyncio.run(_send(args, data, peers))


async def _send(args: argparse.Namespace, data: bytes, peers: list[int]) -> int:
    import asyncio

    from transports.uwb import arq
    from transports.uwb.link import UwbLink

    delivered: set[int] = set()
    failed: dict[int, str] = {}
    done = asyncio.Event()
    loop = asyncio.get_running_loop()
    cfg = _config(args, len(data))
    silence = Silence(peers, cfg.peer_timeout_s, SILENT_TIMEOUTS * cfg.peer_timeout_s)

    def on_event(e: arq.Event) -> None:
        silence.event(e, loop.time())
        if isinstance(e, arq.MessageDelivered):
            delivered.add(e.peer)
        elif isinstance(e, arq.MessageFailed):
            failed[e.peer] = e.reason
        elif isinstance(e, arq.MessageClosed):
            done.set()

    async def watch() -> None:
        while not silence.gave_up(loop.time()):
            await asyncio.sleep(POLL_S)
        done.set()

    link = UwbLink(cfg, args.port, baud=args.baud, on_event=on_event)
    await link.start()
    print(
        f"sending {len(data)} bytes on {args.port}, waiting for peer {', '.join(map(str, peers))}",
        file=sys.stderr,
    )
    progress = asyncio.ensure_future(_progress(link, "bytes_tx", len(data)))
    watcher = asyncio.ensure_future(watch())
    error: MapdError | None = None
    try:
        t0 = loop.time()
        link.send(data, peers, deadline_s=args.deadline)
        try:
            await link.run_until(done.wait())
        except MapdError as exc:  # the link stopped (the port gone): reported with the figures below
            error = exc
        dt = loop.time() - t0
        stats = link.stats()
    finally:
        progress.cancel()
        watcher.cancel()
        await link.close()
    if error is None and (failed or silence.pending):
        error = TransportError(_not_acknowledged(args, silence, failed, dt))
    if error is not None:
        line = f"send {args.file} on {args.port} failed after {dt:.2f} s: {_heard(stats)}"
        summary = {
            "line": line,
            "bytes": len(data),
            "seconds": dt,
            "goodput_bps": None,
            "peers": sorted(delivered),
        }
        _report(args, summary, stats, error)
        raise error
    words, goodput = _goodput(args, len(data), dt)
    line = (
        f"sent {args.file}: {len(data)} bytes to peer {', '.join(map(str, sorted(delivered)))} in {dt:.2f} s, "
        + words
    )
    summary = {
        "line": line,
        "bytes": len(data),
        "seconds": dt,
        "goodput_bps": goodput,
        "peers": sorted(delivered),
    }
    _report(args, summary, stats)
    return 0


def _not_acknowledged(args: argparse.Namespace, silence: Silence, failed: dict[int, str], dt: float) -> str:
    """Why ``send`` failed, in one line that tells a file sent but not acknowledged (the receiver may
    well hold it) from one that never wholly went out, or went to a peer never heard from at all."""
    why: dict[int, str | None] = {}  # None: sent, not acknowledged
    for p in sorted(silence.pending | failed.keys()):
        reason = failed.get(p)
        if reason is not None and reason != "deadline":
            why[p] = reason
        elif reason is not None and p not in silence.heard:
            why[p] = (
                "nothing heard from it: is 'mapd link recv' running there, with the same --baud, "
                "--rate-bps and --key?"
            )
        elif reason is not None and silence.flushed_at is None:
            why[p] = "deadline: not wholly sent"
        else:
            why[p] = None
    if all(w is None for w in why.values()):
        cause = (
            f"not within --deadline {args.deadline:g} s"
            if failed
            else f"nothing heard from it for {silence.silent_s:.0f} s after the whole file was on the air"
        )
        return (
            f"uwb: {args.file} was sent but not acknowledged by peer {', '.join(map(str, why))}: {cause} "
            "(its last ack may have been lost, or it left: see what recv printed)"
        )
    who = ", ".join(f"{p} ({w or 'sent, not acknowledged'})" for p, w in why.items())
    return f"uwb: {args.file} was not delivered to peer {who} after {dt:.1f} s"


def cmd_recv(args: argparse.Namespace) -> int:
    import asyncio

    # before the link starts: checked after the transfer, the sender reported success for data the
    # receiver then threw away
    check_writable(args.output, "-o")
    return asyncio.run(_recv(args))


async def _recv(args: argparse.Namespace) -> int:
    import asyncio

    from mapd.config import LimitsSection
    from transports.uwb import arq
    from transports.uwb.link import UwbLink

    got: asyncio.Future[arq.MessageReceived] = asyncio.get_running_loop().create_future()

    def on_event(e: arq.Event) -> None:
        if isinstance(e, arq.MessageReceived) and not got.done() and args.peer in (None, e.src):
            got.set_result(e)

    limit = LimitsSection().max_message_bytes
    cfg = _config(args, limit)
    link = UwbLink(cfg, args.port, baud=args.baud, on_event=on_event)
    await link.start()
    print(f"waiting for the peer on {args.port}", file=sys.stderr)
    progress = asyncio.ensure_future(_progress(link, "bytes_rx", None))
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    received = False
    try:
        try:
            msg = await asyncio.wait_for(link.run_until(got), args.timeout)
        except TimeoutError:
            raise TransportError(
                f"uwb: no complete message on {args.port} within {args.timeout:.0f} s"
            ) from None
        t_done = loop.time()
        progress.cancel()
        t_first = link.first_rx_at or link.started_at
        received = True  # (a failed write from here on is the file's, not the link's)
        _write(args.output, msg.data)
        # Answer the sender's repeats (our last COMPLETEs may have been lost) until it goes quiet.
        quiet = Quiet(args.linger, LINGER_MAX_S, loop.time())
        while not quiet.over(now := loop.time()):
            quiet.heard(int(link.stats().get("bytes_rx") or 0), now)
            await link.run_until(asyncio.sleep(POLL_S))
        stats = link.stats()
    except MapdError as exc:
        if received:  # the message came whole: the error (a full disk, say) is its own one line
            raise
        dt = loop.time() - t0
        stats = link.stats()
        line = f"recv on {args.port} failed after {dt:.2f} s: {_heard(stats)}"
        _report(
            args, {"line": line, "bytes": None, "seconds": dt, "goodput_bps": None, "peer": None}, stats, exc
        )
        raise
    finally:
        progress.cancel()
        await link.close()
    dt = max(t_done - t_first, 1e-9)
    words, goodput = _goodput(args, len(msg.data), dt)
    line = (
        f"received {args.output}: {len(msg.data)} bytes from peer {msg.src}, hash verified, in {dt:.2f} s "
        f"since the first byte, {words}"
    )
    summary = {"line": line, "bytes": len(msg.data), "seconds": dt, "goodput_bps": goodput, "peer": msg.src}
    _report(args, summary, stats)
    return 0


def _write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".part")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise TransportError(f"{path}: cannot write: {exc.strerror}") from None
    print(f"wrote {path} ({len(data)} bytes)", file=sys.stderr)
