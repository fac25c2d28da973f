"""The ROS 2 tests' fixtures: an independent rmw_zenoh peer (rmw_peer.py) and free loopback endpoints."""

from __future__ import annotations

import importlib.util
import socket
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("rosbags")
pytest.importorskip("xxhash")


def _load_peer() -> ModuleType:
    # --import-mode=importlib keeps test folders off sys.path: load the fixture module by path.
    name = "mapd_tests_rmw_peer"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name("rmw_peer.py"))
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.fixture
def rmw_peer() -> ModuleType:
    """The independent rmw_zenoh implementation (``RmwPeer``, ``parse``, ``gid``, ``GRID``, ``TF``...)."""
    return _load_peer()


@pytest.fixture
def endpoint() -> str:
    return free_endpoint()


@pytest.fixture
def peers(rmw_peer: ModuleType) -> Iterator[list[Any]]:
    """Peers a test opens (``peers.append(rmw_peer.RmwPeer(...))``), closed at the end."""
    opened: list[Any] = []
    yield opened
    for p in opened:
        p.close()
