"""The demo's and the tests' loopback ports come from outside the kernel's ephemeral range.

CI once failed with "Address already in use": a port picked by binding port 0 (an ephemeral
one) was taken by another test worker's outgoing zenoh connection before the daemon bound it.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from mapd.demo import ports


def test_a_free_port_is_outside_the_ephemeral_range_and_bindable() -> None:
    lo, hi = ports.ephemeral_range()
    for _ in range(50):
        port = ports.free_port()
        assert not lo <= port <= hi
        assert port >= ports.LOWEST
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # free, as said


def test_a_port_someone_listens_on_is_never_handed_out(monkeypatch: pytest.MonkeyPatch) -> None:
    held = socket.socket()
    try:
        held.bind(("127.0.0.1", ports.free_port()))
        held.listen()
        taken = held.getsockname()[1]
        other = ports.free_port()
        picks = iter([taken, taken, other])
        monkeypatch.setattr(ports._random, "randint", lambda a, b: next(picks))
        assert ports.free_port() == other  # the held port is tried twice and passed over
    finally:
        held.close()


def test_the_range_is_read_from_the_kernel_file_and_a_bad_file_falls_back(tmp_path: Path) -> None:
    f = tmp_path / "range"
    f.write_text("40000\t50000\n")
    assert ports.ephemeral_range(f) == (40000, 50000)
    for bad in ("", "x y", "50000 40000", "1 99999"):
        f.write_text(bad)
        assert ports.ephemeral_range(f) == ports.DEFAULT_EPHEMERAL
    assert ports.ephemeral_range(tmp_path / "missing") == ports.DEFAULT_EPHEMERAL


def test_a_range_starting_low_picks_above_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ports, "ephemeral_range", lambda: (1024, 49151))  # as on Windows-like tuning
    for _ in range(20):
        assert ports.free_port() > 49151


def test_ports_drawn_together_are_distinct(monkeypatch: pytest.MonkeyPatch) -> None:
    picks = iter([21000, 21000, 21001, 21000, 21002])
    monkeypatch.setattr(ports, "free_port", lambda: next(picks))
    assert ports.free_ports(3) == [21000, 21001, 21002]


def test_endpoint_form() -> None:
    ep = ports.free_endpoint()
    assert ep.startswith("tcp/127.0.0.1:")
    assert not ports.ephemeral_range()[0] <= int(ep.rsplit(":", 1)[1]) <= ports.ephemeral_range()[1]
