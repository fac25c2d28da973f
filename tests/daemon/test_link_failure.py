"""A link whose background work dies stops the daemon with the link's one line.

Before, the UWB serial loop could end on a fault (a signing counter the disk refused) and the
daemon ran on: ``mapd status`` answered, the systemd watchdog was fed, and the robot sent nothing
until someone noticed. Now the daemon watches every transport and stops with that line (exit 1),
so that ``Restart=on-failure`` starts it afresh.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.errors import TransportError
from transports.virtual import VirtualTransport


def test_a_link_that_stops_stops_the_daemon_with_its_line(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    died = asyncio.Event()

    async def watch(self: VirtualTransport) -> None:
        await died.wait()
        raise TransportError("virtual: link stopped: the test pulled its plug")

    monkeypatch.setattr(VirtualTransport, "watch", watch)
    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    sock = tmp_path / "robot0" / "run" / "mapd.sock"

    async def main() -> None:
        run = asyncio.ensure_future(d.run())
        await dk.wait_for(sock.exists, what="the daemon is up")
        await source.queue.put(dk.growing_map(1))
        await dk.wait_for(lambda: d.store.own_map() is not None, what="its first map saved")
        await asyncio.sleep(0.3)
        assert not run.done()  # links at work: the daemon runs on
        died.set()
        with pytest.raises(TransportError) as err:
            await asyncio.wait_for(run, 15)
        assert str(err.value) == "virtual: link stopped: the test pulled its plug"

    asyncio.run(main())
    assert not sock.exists()  # it shut down in order: the status socket is gone
