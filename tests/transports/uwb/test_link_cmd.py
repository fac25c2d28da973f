"""``mapd link send | recv`` as real processes over a socat pty pair: what each end says, and when."""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from mapd.errors import MapdError
from transports.uwb import wire
from transports.uwb.faults import Faults
from transports.uwb.framing import decode_frame
from transports.uwb.relay import FaultRelay

pytestmark = [
    pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed"),
    pytest.mark.timeout(120),
]

EXE = [sys.executable, "-m", "mapd.cli"]
COMMON = ["--rate-bps", "100000"]


async def _pair(
    src: Path,
    out: Path,
    *send_args: str,
    faults: Faults | None = None,
    seed: int = 0,
    recv_args: tuple[str, ...] = ("--linger", "0.5"),
    relay_type: type[FaultRelay] = FaultRelay,
    recv_timeout: float = 20,
) -> tuple[int, str, str, int, str, str]:
    """Run ``recv -o out`` and ``send src`` on the two ends of one relay; both exit codes and outputs."""
    async with relay_type(rate_bps=100_000, faults=faults or Faults(), seed=seed) as relay:
        recv = await asyncio.create_subprocess_exec(
            *EXE, "link", "recv", "--port", relay.ports[1], "-o", str(out), *recv_args,
            "--timeout", str(recv_timeout), *COMMON,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        await asyncio.sleep(0.3)
        send = await asyncio.create_subprocess_exec(
            *EXE, "link", "send", "--port", relay.ports[0], str(src), *COMMON, *send_args,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        s_out, s_err = await asyncio.wait_for(send.communicate(), 80)
        r_out, r_err = await asyncio.wait_for(recv.communicate(), 80)
    assert send.returncode is not None and recv.returncode is not None
    return send.returncode, s_out.decode(), s_err.decode(), recv.returncode, r_out.decode(), r_err.decode()


class _CompletesLost(FaultRelay):
    """Drops the receiver's (robot 1's) COMPLETE acks for ``LOST_S`` after the first one (for ever
    with ``inf``): what a lossy radio does to the last acks of a transfer, made certain."""

    LOST_S = 5.0

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.first_complete: float | None = None
        self.lost = 0

    def _launch(self, src: int, frame: bytes, now: float) -> None:
        if src == 1 and _is_complete(frame):
            self.first_complete = self.first_complete if self.first_complete is not None else now
            if now < self.first_complete + self.LOST_S:
                self.lost += 1
                return
        super()._launch(src, frame, now)


class _CompletesNeverHeard(_CompletesLost):
    LOST_S = math.inf


def _is_complete(frame: bytes) -> bool:
    try:
        body = wire.parse(decode_frame(frame.rstrip(b"\x00")))
    except MapdError:
        return False
    return isinstance(body, wire.Ack) and bool(body.flags & wire.COMPLETE)


async def _recv_alone(out: Path, *args: str) -> tuple[int, str, str]:
    """Run ``recv -o out`` on one end of a relay whose other end nobody opens: a dead radio."""
    async with FaultRelay(rate_bps=100_000) as relay:
        recv = await asyncio.create_subprocess_exec(
            *EXE, "link", "recv", "--port", relay.ports[1], "-o", str(out), *COMMON, *args,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        r_out, r_err = await asyncio.wait_for(recv.communicate(), 30)
    assert recv.returncode is not None
    return recv.returncode, r_out.decode(), r_err.decode()


def _one_error(err: str) -> str:
    errors = [ln.removeprefix("mapd: error: ") for ln in err.splitlines() if ln.startswith("mapd: error: ")]
    assert len(errors) == 1 and "Traceback" not in err, err
    return errors[0]


@pytest.mark.parametrize("where", ["missing folder", "a folder"])
def test_recv_refuses_an_output_it_cannot_write_before_the_link_starts(tmp_path: Path, where: str) -> None:
    src = tmp_path / "map.bin"
    src.write_bytes(b"x" * 3000)
    out = tmp_path / "missing" / "got.bin" if where == "missing folder" else tmp_path
    s_rc, _s_out, s_err, r_rc, _r_out, r_err = asyncio.run(_pair(src, out, "--deadline", "2"))
    assert "Traceback" not in r_err
    errors = [ln for ln in r_err.splitlines() if ln.startswith("mapd: error: ")]
    assert r_rc == 2 and len(errors) == 1, r_err
    assert errors[0].startswith(f"mapd: error: -o {out}: ")
    assert "does not exist" in errors[0] if where == "missing folder" else "is a folder" in errors[0]
    assert "waiting for the peer" not in r_err  # refused before the link started
    # No receiver listened, so the sender must not report a delivery the receiver then threw away.
    assert s_rc == 1 and "was not delivered" in s_err, s_err


def test_a_tiny_file_reports_no_goodput_but_says_why(tmp_path: Path) -> None:
    src = tmp_path / "tiny.bin"
    src.write_bytes(b"hello")
    out = tmp_path / "got.bin"
    s_rc, s_out, s_err, r_rc, r_out, r_err = asyncio.run(_pair(src, out))
    assert s_rc == 0 and r_rc == 0, s_err + r_err
    assert out.read_bytes() == b"hello"
    sent = s_out.splitlines()[0]
    # Within the pacer's first burst the time says nothing about the link: no b/s, no percentage.
    assert "goodput too short to measure" in sent and "%" not in sent, sent
    assert "goodput too short to measure" in r_out and "%" not in r_out.splitlines()[0]
    assert "waiting for the peer on " in r_err and "waiting for peer 2" in s_err


def test_mapd_link_send_and_recv_commands(tmp_path: Path) -> None:
    """A file across a lossy link (2 % of frames dropped), byte for byte, with both ends' figures."""
    src = tmp_path / "map.bin"
    src.write_bytes(os.urandom(15_000))
    out = tmp_path / "got.bin"
    s_rc, s_out, s_err, r_rc, r_out, r_err = asyncio.run(_pair(src, out, faults=Faults(drop=0.02), seed=4))
    assert s_rc == 0, s_err
    assert r_rc == 0, r_err
    assert "goodput" in s_out and "resends=" in s_out
    assert "hash verified" in r_out and "damaged=" in r_out  # crc_errors and the rest, as one total
    assert out.read_bytes() == src.read_bytes()


def test_a_keyed_link_says_how_many_frames_the_line_damaged(tmp_path: Path) -> None:
    """Audit finding 4: on a keyed link the tag replaces the CRC, so damage counts in bad_signature,
    and the link line said crc_errors=0 bad_frames=0 on a line that damaged a third of its frames."""
    key = tmp_path / "link.key"
    key.write_text(bytes(range(32)).hex() + "\n")
    src = tmp_path / "map.bin"
    src.write_bytes(os.urandom(15_000))
    out = tmp_path / "got.bin"
    keyed = ("--key", str(key))
    s_rc, _s_out, s_err, r_rc, r_out, r_err = asyncio.run(
        _pair(src, out, *keyed, faults=Faults(flip=2e-3), seed=4, recv_args=("--linger", "0.5", *keyed))
    )
    assert s_rc == 0 and r_rc == 0, s_err + r_err
    assert out.read_bytes() == src.read_bytes()
    link = next(ln for ln in r_out.splitlines() if ln.startswith("link: "))
    m = re.search(r"damaged=(\d+) \(([^)]*)\)", link)
    assert m is not None, link
    parts = dict(p.split("=") for p in m.group(2).split())
    assert int(m.group(1)) == sum(map(int, parts.values())) > 5 and int(parts["bad_signature"]) > 0, link
    assert "crc_errors=" not in link  # the total says it; crc_errors alone was 0 on every keyed link


def test_recv_answers_the_senders_late_probes_when_its_last_acks_were_lost(tmp_path: Path) -> None:
    """Audit finding 5: recv lingered 3 s after completing while the sender's probes back off to
    max_rto_s (4 s); with its COMPLETEs lost meanwhile the sender, unanswered, reported a delivered
    file as not delivered after its whole deadline."""
    src = tmp_path / "map.bin"
    src.write_bytes(os.urandom(15_000))
    out = tmp_path / "got.bin"

    async def run() -> tuple[tuple[int, str, str, int, str, str], float]:
        t0 = time.monotonic()
        res = await _pair(src, out, "--deadline", "40", recv_args=(), relay_type=_CompletesLost)
        return res, time.monotonic() - t0

    (s_rc, s_out, s_err, r_rc, r_out, r_err), took = asyncio.run(run())
    assert r_rc == 0 and "hash verified" in r_out, r_err
    assert s_rc == 0, s_err  # the sender heard a COMPLETE after the 5 s in which they were lost
    assert "sent " in s_out and out.read_bytes() == src.read_bytes()
    assert took < 30


def test_recv_lingers_for_three_of_the_senders_longest_retransmission_waits() -> None:
    from mapd.commands.link import LINGER_S
    from transports.uwb.arq import ArqConfig

    assert 3 * ArqConfig(node_id=1).max_rto_s <= LINGER_S


def test_send_stops_waiting_for_a_peer_gone_silent_and_says_it_was_sent(tmp_path: Path) -> None:
    """Audit finding 5: a receiver that got the file and left (its COMPLETEs lost) kept the sender
    waiting its whole deadline, which then said "not delivered (deadline)"."""
    src = tmp_path / "map.bin"
    src.write_bytes(os.urandom(15_000))
    out = tmp_path / "got.bin"

    async def run() -> tuple[tuple[int, str, str, int, str, str], float]:
        t0 = time.monotonic()
        res = await _pair(
            src,
            out,
            *("--deadline", "70", "--peer-timeout", "6"),
            recv_args=("--linger", "0"),
            relay_type=_CompletesNeverHeard,
        )
        return res, time.monotonic() - t0

    (s_rc, _s_out, s_err, r_rc, _r_out, r_err), took = asyncio.run(run())
    assert r_rc == 0 and out.read_bytes() == src.read_bytes(), r_err
    errors = [ln for ln in s_err.splitlines() if ln.startswith("mapd: error: ")]
    assert s_rc == 1 and len(errors) == 1, s_err
    assert "was sent but not acknowledged by peer 2" in errors[0], errors[0]
    assert "nothing heard from it for 12 s" in errors[0] and "its last ack may have been lost" in errors[0]
    assert (
        took < 40
    )  # two peer timeouts (--peer-timeout 6) after the whole file went out, not the 70 s deadline


@pytest.mark.parametrize("form", ["json", "text"])
def test_a_failed_recv_and_send_print_their_figures_that_tell_a_wrong_key(tmp_path: Path, form: str) -> None:
    """Docs review: a failed recv or send printed the error alone (with --json, nothing on stdout),
    so a wrong --key, a wrong --baud and a dead radio all read the same, when commissioning needs
    the figures most."""
    key_a, key_b = tmp_path / "a.key", tmp_path / "b.key"
    key_a.write_text(bytes(range(32)).hex() + "\n")
    key_b.write_text(bytes(range(1, 33)).hex() + "\n")
    src = tmp_path / "map.bin"
    src.write_bytes(os.urandom(3000))
    out = tmp_path / "got.bin"
    as_json = ("--json",) if form == "json" else ()
    s_rc, s_out, s_err, r_rc, r_out, r_err = asyncio.run(
        _pair(
            src,
            out,
            *("--key", str(key_b), "--deadline", "3", *as_json),
            recv_args=("--key", str(key_a), *as_json),
            recv_timeout=2,
        )
    )
    r_error, s_error = _one_error(r_err), _one_error(s_err)
    assert r_rc == 1 and r_error.startswith("uwb: no complete message on "), r_err
    assert s_rc == 1 and "was not delivered to peer 2" in s_error, s_err
    assert not out.exists()
    if form == "json":
        doc, sent = json.loads(r_out), json.loads(s_out)  # one document each, whole
        assert doc["ok"] is False and doc["error"] == r_error, doc
        st = doc["stats"]
        # Every frame came whole and failed the tag: another key, not a dead line nor another baud.
        assert st["bytes_rx"] > 0 and st["frames_rx"] == 0 and st["bad_signature"] > 0, st
        assert doc["damaged"] == st["bad_signature"] and st["crc_errors"] == st["cobs_errors"] == 0
        assert "failed the link tag (another --key?)" in doc["line"], doc["line"]
        assert sent["ok"] is False and sent["error"] == s_error and sent["stats"]["frames_tx"] > 0, sent
    else:
        summary, link = r_out.splitlines()
        assert summary.startswith("recv on ") and "failed after" in summary, r_out
        assert "0 valid frames" in summary and "failed the link tag (another --key?)" in summary, summary
        m = re.search(r" bytes_rx=(\d+) .* damaged=(\d+) \(bad_signature=(\d+)\)", link)
        assert m is not None and link.startswith("link: "), link
        assert int(m.group(1)) > 0 and int(m.group(2)) == int(m.group(3)) > 0, link
        assert s_out.startswith(f"send {src} on ") and "\nlink: bytes_tx=" in s_out, s_out


def test_a_recv_that_heard_nothing_says_so_apart_from_a_wrong_key(tmp_path: Path) -> None:
    """A dead radio (nobody on the other end): the same figures, with nothing received at all."""
    out = tmp_path / "got.bin"
    rc, r_out, r_err = asyncio.run(_recv_alone(out, "--timeout", "1", "--json"))
    error = _one_error(r_err)
    assert rc == 1 and error.startswith("uwb: no complete message on ") and "within 1 s" in error, r_err
    doc = json.loads(r_out)
    assert doc["ok"] is False and doc["error"] == error, doc
    assert doc["stats"]["bytes_rx"] == 0 and doc["damaged"] == 0, doc["stats"]
    assert "nothing heard on the line" in doc["line"], doc["line"]
