"""Parity chunks for broadcast maps: forward erasure coding that repairs different losses at once.

A map broadcast in NACK mode (R16) goes to every robot in range, and each loses different frames.
Resending the chunks they ask for means resending the union of their losses, nearly the whole map
once fifteen robots each lose 15 % of frames, and again for what that round lost. A *parity* chunk
instead stands for any one missing chunk of its block, at every receiver at once, so a repair round
costs what the worst receiver lacks, not what all of them lack together (RFC 5740's NORM repairs
with Reed-Solomon parity for the same reason).

The code is Reed-Solomon over GF(2^8) from ``zfec`` (Tahoe-LAFS's erasure coder): a block of ``k``
chunks and any ``k`` of its shares give the block back, for up to 256 shares. The layout:

* a message of ``count`` chunks is cut into ``B = ceil(count / GROUP)`` blocks, chunk ``i`` in block
  ``i % B`` at position ``i // B`` (interleaved, so a burst of losses spreads over blocks);
* shares ``0 .. k-1`` of a block are its data chunks; parity share ``j`` (``j >= 0``) of block ``b``
  is share ``k_b + j`` and travels as chunk index ``count + j * B + b``, so parity indices follow
  the data's and say their block without a field of their own (:func:`index_limit` bounds them);
* every chunk of a block is zero-padded to the block's longest (the chunk size: only the message's
  last chunk is shorter), so a parity chunk is one chunk size long.

Nothing here keeps a clock or does I/O; the ARQ core decides when parity goes (``arq.py``, R16).
"""

from __future__ import annotations

from collections.abc import Iterable

import zfec

#: Data chunks a block holds at most: half of the code's 256 shares, so every block can have at
#: least as many parity chunks as data chunks.
GROUP = 128
#: Shares per block (zfec's limit, GF(2^8)).
SHARES = 256


def blocks(count: int) -> int:
    """How many blocks a message of ``count`` chunks is cut into."""
    return max(1, -(-count // GROUP))


def block_size(count: int, b: int) -> int:
    """The data chunks of block ``b``: chunks ``b, b + B, b + 2B, ...`` below ``count``."""
    return len(range(b, count, blocks(count)))


def max_parity(count: int) -> int:
    """Parity chunks each block may have: what the code allows its largest block (block 0), and what
    the wire's 16-bit chunk index can still address."""
    nb = blocks(count)
    return max(0, min(SHARES - block_size(count, 0), (0x10000 - count) // nb))


def index_limit(count: int) -> int:
    """The first chunk index past every parity chunk a message of ``count`` chunks may have."""
    return count + blocks(count) * max_parity(count)


def parity_index(count: int, b: int, j: int) -> int:
    """The chunk index of parity share ``j`` of block ``b``."""
    return count + j * blocks(count) + b


def parity_of(count: int, index: int) -> tuple[int, int]:
    """(block, zfec share number) of parity chunk ``index`` (``count <= index < index_limit``)."""
    nb = blocks(count)
    j, b = divmod(index - count, nb)
    return b, block_size(count, b) + j


def block_of(count: int, index: int) -> int:
    """The block of data chunk ``index``."""
    return index % blocks(count)


def per_block(count: int, indices: Iterable[int]) -> dict[int, int]:
    """How many of ``indices`` (data chunks) fall in each block."""
    out: dict[int, int] = {}
    nb = blocks(count)
    for i in indices:
        if 0 <= i < count:
            out[i % nb] = out.get(i % nb, 0) + 1
    return out


def pad_block(chunks: list[bytes], count: int, b: int) -> tuple[bytes, ...]:
    """Block ``b`` of ``chunks`` (all the message's data chunks), each zero-padded to the longest:
    what :func:`encode_parity` takes (a sender makes it once per block)."""
    mine = chunks[b :: blocks(count)]
    width = max(len(c) for c in mine)
    return tuple(c.ljust(width, b"\x00") for c in mine)


def encode_parity(block: tuple[bytes, ...], shares: list[int]) -> list[bytes]:
    """Parity ``shares`` (zfec share numbers, each ``>= k``) of a padded block (:func:`pad_block`)."""
    return list(zfec.Encoder(len(block), SHARES).encode(block, tuple(shares)))


def recover(count: int, b: int, have: dict[int, bytes], parity: dict[int, bytes]) -> dict[int, bytes]:
    """The missing data chunks of block ``b`` (chunk index -> padded bytes) from the data chunks held
    (``have``: chunk index -> bytes) and parity held (``parity``: zfec share number -> bytes), or {}
    when there are not enough of them. The caller trims the message's last chunk. ValueError when
    the lengths cannot be one block's (a forged or garbled parity chunk): a wrong parity chunk of
    the right length gives wrong data, which the message hash then refuses."""
    nb = blocks(count)
    k = block_size(count, b)
    if len(have) + len(parity) < k or len(have) >= k:
        return {}
    width = max(len(p) for p in parity.values())
    if any(len(p) != width for p in parity.values()) or any(len(d) > width for d in have.values()):
        raise ValueError("parity chunks of unequal length, or shorter than a data chunk")
    nums: list[int] = []
    bufs: list[bytes] = []
    for i, data in have.items():
        nums.append(i // nb)
        bufs.append(data.ljust(width, b"\x00"))
    for share, data in parity.items():
        if len(nums) >= k:
            break
        nums.append(share)
        bufs.append(data)
    got = zfec.Decoder(k, SHARES).decode(tuple(bufs[:k]), tuple(nums[:k]))
    return {b + pos * nb: bytes(got[pos]) for pos in range(k) if b + pos * nb not in have}
