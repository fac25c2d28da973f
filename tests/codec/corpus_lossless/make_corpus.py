"""Rebuild the crafted entries of this corpus: ``.venv/bin/python tests/codec/corpus_lossless/make_corpus.py``.

Needed only when the lossless model version changes (the payloads carry it). Entries found by
fuzzing are added by hand (see README.md) and are not touched by this script.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # tests/, for conftest
from conftest import make_room_grid

from mapd.codec import encode, read_header
from mapd.codec.api import _FIXED
from mapd.grid import OccupancyGrid

out = Path(__file__).resolve().parent
base = make_room_grid(seed=0).replace(version=1)
d = base.data.copy()
d[10:20, 10:20] = 0
d[30, 5:50] = 100
new = OccupancyGrid(d, base.resolution, base.origin, version=2)
whole = encode(base, "lossless")
delta = encode(new, "lossless", base=base, options=None)
assert read_header(delta).delta
(out / "base.raw").write_bytes(encode(base, "raw"))


def rebody(
    payload: bytes, body: bytes, *, delta: bool | None = None, dims: tuple[int, int] | None = None
) -> bytes:
    h = read_header(payload)
    head = bytearray(payload[: h.body_offset])
    fixed_at = h.body_offset - _FIXED.size
    f = list(_FIXED.unpack_from(head, fixed_at))
    f[-1] = len(body)
    if dims is not None:
        f[0], f[1] = dims
    if delta is not None:
        head[5] = (head[5] & ~1) | (1 if delta else 0)
        if delta:
            f[6] = base.version
            f[7] = base.digest()
        else:
            f[6] = 0
            f[7] = bytes(16)
    _FIXED.pack_into(head, fixed_at, *f)
    return bytes(head) + body


wb = whole[read_header(whole).body_offset :]
db = delta[read_header(delta).body_offset :]
entries: list[dict[str, str | None]] = []


def add(name: str, payload: bytes, use_base: bool, error: str, why: str) -> None:
    (out / f"{name}.bin").write_bytes(payload)
    entries.append(
        {
            "file": f"{name}.bin",
            "base": "base.raw" if use_base else None,
            "error": error,
            "why": why,
            "found": "crafted",
        }
    )


add("empty-body", rebody(whole, b""), False, "body is empty", "a header with a zero-length body")
add(
    "other-model-version",
    rebody(whole, bytes([wb[0] | 0xF8]) + wb[1:]),
    False,
    "model version 31",
    "a payload from another model version",
)
add(
    "unknown-mode",
    rebody(whole, bytes([(wb[0] & ~3) | 2]) + wb[1:]),
    False,
    "unknown mode",
    "mode 2 is not defined",
)
add(
    "delta-body-whole-header",
    rebody(delta, db, delta=False),
    False,
    "says it is a whole map",
    "body is a delta, header says whole map",
)
add(
    "whole-body-delta-header",
    rebody(whole, wb, delta=True),
    True,
    "says it is a delta",
    "body is a whole map, header says delta",
)
add(
    "overlong-varint",
    rebody(delta, bytes([db[0]]) + b"\x80\x80\x80\x80\x80\x01" + db[3:]),
    True,
    "overlong offset varint",
    "six varint bytes",
)
add(
    "nonminimal-varint",
    rebody(delta, bytes([db[0]]) + b"\x80\x00\x00" + db[3:]),
    True,
    "non-minimal offset varint",
    "zero continuation byte",
)
add(
    "absurd-offset",
    rebody(delta, bytes([db[0]]) + b"\xfe\xff\xff\xff\x7f\x00" + db[3:]),
    True,
    "absurd delta offset",
    "offset beyond 32 bits",
)
add(
    "offset-mismatch",
    rebody(delta, bytes([db[0]]) + b"\x06\x00" + db[3:]),
    True,
    "does not match the origins",
    "offset (3, 0) for grids that share an origin",
)
add(
    "varint-truncated",
    rebody(delta, bytes([db[0]]) + b"\x80"),
    True,
    "truncated in its delta offsets",
    "body ends inside a varint",
)
add("stream-truncated", rebody(whole, wb[:-1]), False, "truncated or corrupt", "last stream byte cut off")
add("stream-trailing-byte", rebody(whole, wb + b"\x00"), False, "truncated or corrupt", "one byte too many")
add(
    "stream-all-ones",
    rebody(whole, bytes([wb[0]]) + b"\xff" * 40),
    False,
    "truncated or corrupt",
    "a stream of 0xff bytes",
)
add("delta-stream-truncated", rebody(delta, db[:-2]), True, "truncated or corrupt", "delta stream cut short")
flip = bytearray(wb)
flip[len(flip) // 2] ^= 0x10
add(
    "stream-bit-flip",
    rebody(whole, bytes(flip)),
    False,
    "truncated or corrupt",
    "one flipped bit in the middle of the stream",
)
add(
    "dims-changed",
    rebody(whole, wb, dims=(base.height + 1, base.width)),
    False,
    "does not match its checksum",
    "header claims one more row than was coded",
)
add(
    "dims-huge",
    rebody(whole, wb, dims=(1 << 20, 1 << 20)),
    False,
    "over the limit",
    "header claims 2**40 cells",
)
add(
    "trinary-flag-cleared",
    rebody(whole, bytes([wb[0] & ~4]) + wb[1:]),
    False,
    "truncated or corrupt",
    "trinary flag cleared: the model differs",
)
manifest = out / "manifest.json"
kept = (
    [e for e in json.loads(manifest.read_text()) if e.get("found") != "crafted"] if manifest.exists() else []
)
manifest.write_text(json.dumps(kept + entries, indent=1) + "\n")
print(f"{len(entries)} crafted entries written, {len(kept)} other entries kept")
