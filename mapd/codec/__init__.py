"""Map codecs: ``encode(grid, codec, base)`` and ``decode(payload, base)`` over codec plugins."""

from mapd.codec.api import Header, decode, encode, get_codec, read_header
from mapd.codec.base import Codec, CodecOptions, Encoded, Target

__all__ = [
    "Codec",
    "CodecOptions",
    "Encoded",
    "Header",
    "Target",
    "decode",
    "encode",
    "get_codec",
    "read_header",
]
