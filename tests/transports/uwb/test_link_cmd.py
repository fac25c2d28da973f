"""``mapd link send | recv`` as real processes over a socat pty pair: what each end says, and when."""

from __future__ import annotations

import asyncio
import os
import shutil
import sys
from pathlib import Path

import pytest

from transports.uwb.faults import Faults
from transports.uwb.relay import FaultRelay

pytestmark = [
    pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed"),
    pytest.mark.timeout(60),
]

EXE = [sys.executable, "-m", "mapd.cli"]
COMMON = ["--rate-bps", "100000"]


async def _pair(
    src: Path, out: Path, *send_args: str, faults: Faults | None = None, seed: int = 0
) -> tuple[int, str, str, int, str, str]:
    """Run ``recv -o out`` and ``send src`` on the two ends of one relay; both exit codes and outputs."""
    async with FaultRelay(rate_bps=100_000, faults=faults or Faults(), seed=seed) as relay:
        recv = await asyncio.create_subprocess_exec(
            *EXE, "link", "recv", "--port", relay.ports[1], "-o", str(out), "--linger", "0.5",
            "--timeout", "20", *COMMON,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        await asyncio.sleep(0.3)
        send = await asyncio.create_subprocess_exec(
            *EXE, "link", "send", "--port", relay.ports[0], str(src), *COMMON, *send_args,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        s_out, s_err = await asyncio.wait_for(send.communicate(), 40)
        r_out, r_err = await asyncio.wait_for(recv.communicate(), 40)
    assert send.returncode is not None and recv.returncode is not None
    return send.returncode, s_out.decode(), s_err.decode(), recv.returncode, r_out.decode(), r_err.decode()


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
    assert "hash verified" in r_out and "crc_errors=" in r_out
    assert out.read_bytes() == src.read_bytes()
