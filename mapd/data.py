"""Where the shared real data lives: ``$MAPD_DATA``, else ``../shared/data`` beside the checkout."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def data_dir() -> Path | None:
    """The shared data folder, or None when it is absent (tests that need it then skip)."""
    env = os.environ.get("MAPD_DATA")
    candidates = [Path(env)] if env else [REPO_ROOT.parent / "shared" / "data"]
    for c in candidates:
        if c.is_dir():
            return c
    return None


def shared_maps(root: Path | None = None) -> list[Path]:
    """Every map_server YAML under ``<data>/maps`` (sorted), or [] when there is no data."""
    base = root if root is not None else data_dir()
    if base is None:
        return []
    maps = base / "maps" if (base / "maps").is_dir() else base
    return sorted(maps.rglob("*.yaml"))


def shared_log(name: str = "intel") -> Path | None:
    """A CARMEN log from ``<data>/logs`` by short name (intel, freiburg-079), or None."""
    base = data_dir()
    if base is None:
        return None
    hits = sorted((base / "logs").glob(f"{name}*.log*"))
    return hits[0] if hits else None


def map_label(yaml_path: Path) -> str:
    """A short readable name for a shared map: its folder, e.g. 'radish_derived/intel'."""
    parts = yaml_path.parent.parts
    return "/".join(parts[-2:]) if len(parts) >= 2 else yaml_path.stem
