"""The codec interface: one small ABC every codec plugin implements.

A codec turns the cells of an :class:`~mapd.grid.OccupancyGrid` into a body of bytes and back.
:mod:`mapd.codec.api` wraps the body in the self-describing header (dimensions, resolution, origin,
base, checksum), so a codec only ever thinks about cells.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from mapd.grid import OccupancyGrid, Pose2D


class CodecOptions(BaseModel):
    """Options a codec reads from its ``[codec.<name>]`` table. Subclass to add fields."""

    model_config = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class Target:
    """What the decoder knows about the grid before it reads the body (from the header)."""

    height: int
    width: int
    resolution: float
    origin: Pose2D
    variant: str


@dataclass(frozen=True)
class Encoded:
    """A codec's output: the body, and whether it was coded against the base (a delta)."""

    body: bytes
    delta: bool = False


class Codec(ABC):
    """A map codec. Subclasses set ``name`` and the class flags and implement the two methods.

    ``lossless`` codecs promise ``decode(encode(g)) == g`` cell for cell; the API then checks every
    decoded grid against a digest in the header. ``uses_base`` codecs may code a grid against a base
    version both ends hold; they decide per map whether the delta is worth it.
    """

    name: ClassVar[str]
    lossless: ClassVar[bool] = True
    uses_base: ClassVar[bool] = False
    Options: ClassVar[type[CodecOptions]] = CodecOptions

    def __init__(self, options: CodecOptions | None = None) -> None:
        self.options = options if options is not None else self.Options()

    def variant(self) -> str:
        """A short id of anything the decoder must share (a model id); empty when none."""
        return ""

    def held(self, grid: OccupancyGrid) -> OccupancyGrid:
        """The grid a receiver holds once it has decoded ``grid``: its delta base from then on.

        ``grid`` itself for a lossless codec. A lossy codec with ``uses_base`` overrides this, and
        its decoded cells must depend on ``grid`` alone (not on the base it was coded against), so
        that the sender can name the receiver's base by its digest.
        """
        return grid

    @abstractmethod
    def encode_cells(self, grid: OccupancyGrid, base: OccupancyGrid | None) -> Encoded:
        """Code ``grid``'s cells; ``base`` is given only when ``uses_base`` and a base exists."""

    @abstractmethod
    def decode_cells(self, body: bytes, target: Target, base: OccupancyGrid | None) -> np.ndarray:
        """Return int8 cells of shape ``(target.height, target.width)``.

        ``base`` is the grid the body was coded against, when the header marks it a delta.
        Raise :class:`~mapd.errors.CodecError` on anything malformed; never allocate more than
        the target's size implies.
        """
