"""An outsider on the radio: two signed daemons over socat ptys through the relay, a rogue on a third port.

Measured on main (unsigned by default): a 13-byte forged HELLO with the sender's link id made both
sides fail at their 60 s deadline; a 25-byte forged REJECT made the sender give up in 3.7 s; 64
fake link ids kept alive meant a robot joining later was never heard. With the fleet's link key
(the default), frames without a valid tag are dropped before the protocol looks at them.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.demo.fleet import Fleet
from transports.uwb import wire
from transports.uwb.framing import encode_frame
from transports.uwb.signing import Signer

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed"),
]


def forgeries(session_of: dict[int, int]) -> list[bytes]:
    """HELLOs as robot0 and robot1 with new sessions, a REJECT and a COMPLETE for their messages,
    64 fake link ids, and the same frames 'signed' with a key that is not the fleet's."""
    bodies = []
    for src, dst in ((1, 2), (2, 1)):
        bodies.append(wire.pack(wire.Hello(src, wire.BROADCAST, random.getrandbits(24))))
        for msg in range(1, 40):
            for flags in (wire.REJECT, wire.COMPLETE):
                ack = wire.Ack(
                    src, dst, session_of.get(src, 1), session_of.get(dst, 1), msg, 0, flags, 0, b""
                )
                bodies.append(wire.pack(ack))
    bodies += [wire.pack(wire.Hello(i, wire.BROADCAST, i)) for i in range(100, 164)]
    wrong = Signer(os.urandom(32), 10**12, block=4096)
    wrong.confirm(10**12 + 4096)
    signed = [wrong.sign(wire.pack(wire.Hello(1, wire.BROADCAST, 7), signed=True)) for _ in range(20)]
    return [encode_frame(b) for b in bodies + signed]


def test_forged_hello_reject_and_fake_link_ids_do_not_stop_a_signed_transfer(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    args = argparse.Namespace(
        robots=3, transport="uwb", codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0
    )
    f = Fleet(args)
    f.prepare()
    f.names = ["robot0", "robot1"]  # robot2's port is the rogue's radio
    f.start()
    rogue_port = f.ports["robot2"]
    try:
        snaps = fk.wait_for(lambda s: fk.held(s, "robot1", "robot0") >= 2, 120, f)
        before = fk.held(snaps, "robot1", "robot0")
        assert before >= 2, json.dumps(snaps)[:2000]
        fd = os.open(rogue_port, os.O_RDWR | os.O_NOCTTY)
        try:
            frames = forgeries({})
            for _ in range(3):  # a few rounds, paced so the 12.5 kb/s radio carries them
                for fr in frames:
                    os.write(fd, fr)
                    time.sleep(len(fr) * 8 / 12_500)
        finally:
            os.close(fd)
        snaps = fk.wait_for(lambda s: fk.held(s, "robot1", "robot0") >= before + 3, 90, f)
        assert fk.held(snaps, "robot1", "robot0") >= before + 3
        for me, other in (("robot0", "robot1"), ("robot1", "robot0")):
            link = snaps[me]["links"]["uwb"]
            # the rogue's frames were dropped before the protocol saw them, and counted
            assert link["unsigned"] > 0 and link["bad_signature"] > 0, link
            assert link["peers"] == [other], link  # no fake link id became a peer
            assert snaps[me]["counters"]["updates_received"] >= 1
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    for name in ("robot0", "robot1"):
        log = (f.run_dir / name / "daemon.log").read_text(errors="replace")
        assert "Traceback" not in log, log[-3000:]
