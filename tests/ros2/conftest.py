"""The ROS 2 tests' fixtures: an independent rmw_zenoh peer (rmw_peer.py) and free loopback endpoints."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from mapd.demo.fleet import write_config
from mapd.demo.ports import free_endpoint
from mapd.identity import Identity

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


def write_base_config(root: Path, tables: dict[str, dict[str, Any]]) -> Path:
    """A signed config for a base station named ``base`` in fleet ``lab`` (its key and state under
    ``root``) with the ``ros2`` source, plus ``tables`` (``source.ros2``, ``fusion``, ``output``...)."""
    root.mkdir(parents=True, exist_ok=True)
    key = root / "base.key"
    identity = Identity.generate("base")
    identity.write(key)
    path = root / "config.toml"
    write_config(
        path,
        {
            "robot": {"name": "base", "fleet": "lab", "key_file": str(key)},
            "fleet": {"roster": {"base": identity.public_text}},
            "state": {"dir": str(root / "state"), "runtime_dir": str(root / "run")},
            "source": {"use": "ros2"},
            **tables,
        },
    )
    return path


@pytest.fixture
def base_config() -> Callable[[Path, dict[str, dict[str, Any]]], Path]:
    """:func:`write_base_config`, for test modules (importlib mode keeps conftest out of their imports)."""
    return write_base_config
