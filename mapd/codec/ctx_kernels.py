"""The compiled heart of the ``lossless`` codec: arithmetic coder, context models, both kernels.

**Why one file.** numba's on-disk cache (``cache=True``) checks only the source file that defines a
compiled function, not the files of the functions it calls and compiles into itself. Were the coder
or a helper in another module, editing it would leave stale kernels in the cache, and two robots
could disagree on the model. So everything numba compiles for this codec, and every constant it
bakes in, lives here. ``tests/codec/test_lossless_kernels.py`` checks that this stays so.

**The coder.** The model predicts one binary decision at a time from the cells decoded just before
it, so the decoder must call the coder once per decision, millions of times per map.
``constriction`` is a good coder, but a Python-level call per decision costs microseconds, about a
hundred times the budget. The coder here (the carry-less 32-bit binary arithmetic coder of the
PAQ/lpaq family, with 16-bit probabilities) is a dozen lines that numba compiles into the same loop
as the model, so a decision costs nanoseconds.

Everything is integer arithmetic: encoder and decoder may run on different machines (x86 and ARM
robots), and a float rounding difference between them would desynchronise the model. The logistic
tables are built from a fixed list of knots by integer interpolation for the same reason.

Probabilities are ``P(bit = 1)`` in units of 1/65536, in ``[1, 65535]``. Logits ("stretch" domain)
are fixed point with 8 fractional bits, in ``[-XMAX, XMAX]`` (about +-12). Counters keep 22-bit
probabilities and a count that sets their learning rate (1/(n + 1.5) up to a limit). Each decision
is predicted by mixing six counters in the logistic domain with two weight sets chosen by small
contexts, each trained online (PAQ-style context mixing).

**Stream rules** (so that a decoder can tell a truncated or padded body from a good one): the
encoder ends with one flush byte, and the decoder reads past the end as zero bytes. A valid stream
makes the decoder read exactly ``len(body) + 3`` bytes; it stops as soon as it reads more, and it
never decodes more than one value per cell of the target, so corrupt input ends in bounded time.

**Memory.** Besides the output grid: ring buffers of a few rows, direct tables of at most 1 MiB,
and hashed tables sized from the grid (about one context per eight cells, at most ``2**18``
contexts, 4 MiB, per table; four tables).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# ----------------------------------------------------------------------------------------------------
# The binary arithmetic coder, counters and the logistic tables
# ----------------------------------------------------------------------------------------------------

#: Largest logit magnitude (fixed point, 8 fractional bits: 3071/256 = 12.0).
XMAX = 3071
#: 65536 / (1 + exp(-k / 2)) for k = -24..24, rounded and clipped to [1, 65535]; the logistic curve
#: is interpolated between these knots with integers only, so both ends build identical tables.
_KNOTS = (
    1, 1, 1, 2, 3, 5, 8, 13, 22, 36, 60, 98, 162, 267, 439, 720, 1179, 1921, 3108, 4971, 7812, 11955,
    17625, 24743, 32768, 40793, 47911, 53581, 57724, 60565, 62428, 63615, 64357, 64816, 65097, 65269,
    65374, 65438, 65476, 65500, 65514, 65523, 65528, 65531, 65533, 65534, 65535, 65535, 65535,
)  # fmt: skip
#: Bytes the decoder may read past the end of a valid stream (4 read at start, 1 flushed at end).
OVERREAD = 3
#: Counter layout (uint32): probability of a 1 in the high 22 bits, observation count in the low 10.
#: 22 bits, not 16, so that slow counters can still creep towards certainty (a 16-bit probability
#: stops moving once the step rounds to zero, near 1 - 1/64 for the slowest rate).
COUNT_BITS = 10
COUNT_MASK = (1 << COUNT_BITS) - 1
#: ``counter >> P16_SHIFT`` is the probability in 16 bits, as the coder and ``stretch`` take it.
P16_SHIFT = 16
#: Probabilities of counters stay within [PMIN, 2**22 - PMIN] (1/65536 at each end).
PMIN = 64
#: A fresh counter: probability one half, never seen.
COUNTER_INIT = (1 << 21) << COUNT_BITS


def build_tables() -> tuple[np.ndarray, np.ndarray]:
    """``squash`` (int32, logit + XMAX -> probability) and ``stretch`` (int16, probability -> logit)."""
    knots = np.array(_KNOTS, dtype=np.int64)
    x = np.arange(-XMAX, XMAX + 1, dtype=np.int64)
    u = x + 3072
    i = u >> 7
    f = u & 127
    sq = knots[i] + (((knots[i + 1] - knots[i]) * f) >> 7)
    sq = np.clip(sq, 1, 65535).astype(np.int32)
    # stretch is the inverse of squash: the smallest logit whose probability reaches p.
    st = np.searchsorted(sq, np.arange(65536), side="left") - XMAX
    st = np.clip(st, -XMAX, XMAX).astype(np.int16)
    return sq, st


def build_rates(limit: int) -> np.ndarray:
    """Counter step sizes: 1/(n + 1.5) in 16-bit fixed point for a counter seen n times, up to ``limit``."""
    n = np.arange(COUNT_MASK + 1, dtype=np.int64)
    rate = (2 * 65536) // (2 * np.minimum(n, limit) + 3)
    return rate.astype(np.int32)


@njit(cache=True, inline="always")
def encode_bit(
    y: int, p: int, x1: int, x2: int, buf: np.ndarray, pos: int
) -> tuple[int, int, np.ndarray, int]:
    """Code bit ``y`` with ``P(1) = p / 65536``; may grow ``buf`` (returned)."""
    rng = x2 - x1
    xmid = x1 + (rng >> 16) * p + (((rng & 0xFFFF) * p) >> 16)
    if y:
        x2 = xmid
    else:
        x1 = xmid + 1
    while ((x1 ^ x2) & 0xFF000000) == 0:
        if pos >= buf.shape[0]:
            bigger = np.empty(buf.shape[0] * 2, np.uint8)
            bigger[:pos] = buf[:pos]
            buf = bigger
        buf[pos] = x2 >> 24
        pos += 1
        x1 = (x1 << 8) & 0xFFFFFFFF
        x2 = ((x2 << 8) & 0xFFFFFFFF) | 255
    return x1, x2, buf, pos


@njit(cache=True, inline="always")
def decode_bit(p: int, x1: int, x2: int, x: int, buf: np.ndarray, pos: int) -> tuple[int, int, int, int, int]:
    """Decode one bit with ``P(1) = p / 65536``; ``pos`` counts bytes read, zeros past the end."""
    rng = x2 - x1
    xmid = x1 + (rng >> 16) * p + (((rng & 0xFFFF) * p) >> 16)
    if x <= xmid:
        y = 1
        x2 = xmid
    else:
        y = 0
        x1 = xmid + 1
    while ((x1 ^ x2) & 0xFF000000) == 0:
        x1 = (x1 << 8) & 0xFFFFFFFF
        x2 = ((x2 << 8) & 0xFFFFFFFF) | 255
        b = buf[pos] if pos < buf.shape[0] else 0
        pos += 1
        x = ((x << 8) & 0xFFFFFFFF) | b
    return y, x1, x2, x, pos


@njit(cache=True, inline="always")
def code_bit(
    dec: bool, y: int, p: int, x1: int, x2: int, x: int, buf: np.ndarray, pos: int
) -> tuple[int, int, int, int, np.ndarray, int]:
    """Encode ``y`` or (``dec``) decode a bit; one call site keeps the model shared by both ends."""
    if dec:
        y, x1, x2, x, pos = decode_bit(p, x1, x2, x, buf, pos)
    else:
        x1, x2, buf, pos = encode_bit(y, p, x1, x2, buf, pos)
    return y, x1, x2, x, buf, pos


@njit(cache=True, inline="always")
def start_decoder(buf: np.ndarray) -> tuple[int, int]:
    """The decoder's first four bytes as ``x``, and the read position after them."""
    x = 0
    for i in range(4):
        b = buf[i] if i < buf.shape[0] else 0
        x = (x << 8) | b
    return x, 4


@njit(cache=True, inline="always")
def flush_encoder(x1: int, x2: int, buf: np.ndarray, pos: int) -> tuple[np.ndarray, int]:
    """End the stream with one byte that, followed by zeros, lies in ``[x1, x2]``."""
    top = (x1 >> 24) + (1 if (x1 & 0xFFFFFF) != 0 else 0)
    if pos >= buf.shape[0]:
        bigger = np.empty(buf.shape[0] * 2, np.uint8)
        bigger[:pos] = buf[:pos]
        buf = bigger
    buf[pos] = top
    return buf, pos + 1


@njit(cache=True, inline="always")
def start_coder(dec: bool, src: np.ndarray, capacity: int) -> tuple[int, int, int, np.ndarray, int, int]:
    """Coder state ``(x1, x2, x, buf, pos, end)`` at the start of a stream.

    The decoder reads ``src`` and must stop exactly at ``end`` (see the stream rules above); the
    encoder writes into a new buffer of ``capacity`` bytes, which grows when it fills.
    """
    if dec:
        x, pos = start_decoder(src)
        return 0, 0xFFFFFFFF, x, src, pos, src.shape[0] + OVERREAD
    return 0, 0xFFFFFFFF, 0, np.empty(capacity, np.uint8), 0, 0


@njit(cache=True, inline="always")
def finish_coder(dec: bool, x1: int, x2: int, buf: np.ndarray, pos: int, end: int) -> tuple[np.ndarray, int]:
    """What a kernel returns at the end of the grid: the encoder's flushed buffer and its length, or
    the decoder's ``buf`` and 0 when the stream ended exactly where it should, -1 when it did not."""
    if dec:
        return buf, 0 if pos == end else -1
    return flush_encoder(x1, x2, buf, pos)


@njit(cache=True, inline="always")
def update_counter(t: np.ndarray, i: int, y: int, rates: np.ndarray, limit: int, pmin: int) -> None:
    """Move counter ``t[i]`` towards bit ``y`` by its count-dependent rate, within [pmin, 1 - pmin]."""
    v = int(t[i])
    n = v & COUNT_MASK
    p = v >> COUNT_BITS
    p += (((y << 22) - p) * rates[n]) >> 16
    if p < pmin:
        p = pmin
    elif p > (1 << 22) - pmin:
        p = (1 << 22) - pmin
    if n < limit:
        n += 1
    t[i] = (p << COUNT_BITS) | n


@njit(cache=True, inline="always")
def squash(sq: np.ndarray, x: int) -> int:
    """Probability of logit ``x`` (clamped to the table)."""
    if x > XMAX:
        x = XMAX
    elif x < -XMAX:
        x = -XMAX
    return sq[x + XMAX]


# ----------------------------------------------------------------------------------------------------
# Pieces shared by the two models
# ----------------------------------------------------------------------------------------------------

#: log2 of the contexts in each hashed table (four decision slots each) is chosen from the grid's
#: size, between these bounds: 2**18 contexts (four slots of 4 bytes) is 4 MiB per table.
HASH_BITS_MIN = 10
HASH_BITS_MAX = 18
_K1 = -7046029254386353131  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)
_K2 = -4658895280553007687  # 0xBF58476D1CE4E5B9 as int64
#: Version of everything above and below that shapes the bitstream (constants, contexts, tables).
#: Payloads carry it, and a decoder refuses other versions: bump it with any change to the model.
MODEL_VERSION = 1
#: Count limits of the counters (how slowly they settle): context models, escape tree, quiet cells.
#: Context models adapt fast (a low limit measured best on the shared maps); quiet cells slowly.
LIMIT = 16
VALUE_LIMIT = 60
QUIET_LIMIT = 1023
#: Context-model counters stay within about 1/512 of certainty: the mixer does better with inputs
#: that never claim more than the counter's count can back.
MODEL_PMIN = 8192
#: Mixer learning rate (a right shift: larger is slower).
MIX_SHIFT = 15
#: Initial mixer weight of each input (16.16 fixed point).
W_INIT = 65536 // 4
#: Escape-tree counters: 33 predictor buckets (32 byte ranges and "none") of 256 tree nodes.
VALUE_TABLE = 33 * 256


@njit(cache=True, inline="always")
def cell_class(v: int) -> int:
    """0 unknown (-1), 1 free (0), 2 occupied (100), 3 any other value."""
    if v == -1:
        return 0
    if v == 0:
        return 1
    if v == 100:
        return 2
    return 3


@njit(cache=True, inline="always")
def class_value(s: int) -> int:
    """The cell value of classes 0..2."""
    if s == 0:
        return -1
    if s == 1:
        return 0
    return 100


@njit(cache=True, inline="always")
def hashed(ctx: int, salt: int, bits: int) -> int:
    """A slot in a table of ``2**bits`` contexts, with four decision slots in the low two bits."""
    h = (ctx + salt) * _K1
    h = (h ^ (h >> 29)) * _K2
    return ((h >> 32) & ((1 << bits) - 1)) << 2


def hash_bits(cells: int) -> int:
    """Hashed-table size for a grid of ``cells``: about one context per eight cells, within bounds.

    Both ends derive it from the header's dimensions, so memory follows the map's size.
    """
    return max(HASH_BITS_MIN, min(HASH_BITS_MAX, int(cells).bit_length() - 3))


@njit(cache=True, inline="always")
def quant(n: int) -> int:
    """A count in 0..7, finer where counts are small."""
    if n <= 2:
        return n
    if n <= 4:
        return 3
    if n <= 8:
        return 4
    if n <= 16:
        return 5
    if n <= 32:
        return 6
    return 7


@njit(cache=True, inline="always")
def candidates(first: int, excl: int, trinary: bool, out: np.ndarray) -> int:
    """Classes in coding order: ``first`` (if >= 0), then the others ascending, leaving out ``excl``
    and, for a trinary grid, class 3. Returns how many."""
    n = 0
    if first >= 0:
        out[0] = first
        n = 1
    for q in range(4):
        if q == first or q == excl or (trinary and q == 3):  # noqa: SIM109 (numba: plain compares)
            continue
        out[n] = q
        n += 1
    return n


@njit(cache=True)
def model_offsets(direct: np.ndarray, hashed_tables: int, bits: int) -> np.ndarray:
    """Start of each model's counters in one flat table: ``direct`` context counts first, then
    ``hashed_tables`` tables of ``2**bits`` contexts; four decision slots per context."""
    n = direct.shape[0] + hashed_tables
    off = np.zeros(n + 1, np.int64)
    for m in range(n):
        size = direct[m] if m < direct.shape[0] else 1 << bits
        off[m + 1] = off[m] + 4 * size
    return off


@njit(cache=True, inline="always")
def mix_code(
    dec: bool,
    y: int,
    k: int,
    idx: np.ndarray,
    t: np.ndarray,
    wts1: np.ndarray,
    ws1: int,
    wts2: np.ndarray,
    ws2: int,
    sti: np.ndarray,
    sq: np.ndarray,
    st: np.ndarray,
    rates: np.ndarray,
    x1: int,
    x2: int,
    x: int,
    buf: np.ndarray,
    pos: int,
) -> tuple[int, int, int, int, np.ndarray, int]:
    """Code decision slot ``k`` of the contexts ``idx``: mix the models' predictions with two weight
    sets (rows ``ws1`` and ``ws2``), code ``y`` (or decode it), then train counters and weights.

    ``sti`` holds one stretch slot per model plus a bias input fixed at 256.
    """
    nm = idx.shape[0]
    dot1 = 0
    dot2 = 0
    for m in range(nm + 1):
        if m < nm:
            sti[m] = st[t[idx[m] + k] >> P16_SHIFT]
        dot1 += wts1[ws1, m] * sti[m]
        dot2 += wts2[ws2, m] * sti[m]
    pr = squash(sq, (dot1 + dot2) >> 17)
    y, x1, x2, x, buf, pos = code_bit(dec, y, pr, x1, x2, x, buf, pos)
    err1 = (y << 16) - squash(sq, dot1 >> 16)
    err2 = (y << 16) - squash(sq, dot2 >> 16)
    for m in range(nm + 1):
        wts1[ws1, m] += (sti[m] * err1) >> MIX_SHIFT
        wts2[ws2, m] += (sti[m] * err2) >> MIX_SHIFT
    for m in range(nm):
        update_counter(t, idx[m] + k, y, rates, LIMIT, MODEL_PMIN)
    return y, x1, x2, x, buf, pos


@njit(cache=True, inline="always")
def code_quiet(
    dec: bool,
    y: int,
    qt: np.ndarray,
    qi: int,
    rates: np.ndarray,
    x1: int,
    x2: int,
    x: int,
    buf: np.ndarray,
    pos: int,
) -> tuple[int, int, int, int, np.ndarray, int]:
    """Code a decision with one slow adaptive counter ``qt[qi]`` (no mixing)."""
    y, x1, x2, x, buf, pos = code_bit(dec, y, int(qt[qi] >> P16_SHIFT), x1, x2, x, buf, pos)
    update_counter(qt, qi, y, rates, QUIET_LIMIT, PMIN)
    return y, x1, x2, x, buf, pos


@njit(cache=True, inline="always")
def code_escape(
    dec: bool,
    v: int,
    pv: int,
    vt: np.ndarray,
    rates: np.ndarray,
    x1: int,
    x2: int,
    x: int,
    buf: np.ndarray,
    pos: int,
) -> tuple[int, int, int, int, np.ndarray, int]:
    """Code an "other" cell's byte through a binary tree whose counters depend on a predictor byte
    ``pv`` (256: none). Returns the value (decoded, or ``v`` itself) and the coder state."""
    base = (pv >> 3) * 256
    ub = v & 255
    node = 1
    for b in range(7, -1, -1):
        y = (ub >> b) & 1
        j = base + node
        y, x1, x2, x, buf, pos = code_bit(dec, y, int(vt[j] >> P16_SHIFT), x1, x2, x, buf, pos)
        update_counter(vt, j, y, rates, VALUE_LIMIT, PMIN)
        node = node * 2 + y
    out = node - 256
    if out > 127:
        out -= 256
    return out, x1, x2, x, buf, pos


@njit(cache=True, inline="always")
def neighbour_byte(data: np.ndarray, r: int, c: int, west: int, north: int) -> int:
    """The escape path's predictor byte: the value of the west neighbour if its class (``west``) is
    "other", else of the north one if that is, else 256 (none)."""
    if west == 3:
        return int(data[r, c - 1]) & 255
    if north == 3:
        return int(data[r - 1, c]) & 255
    return 256


# ----------------------------------------------------------------------------------------------------
# The whole-map model
# ----------------------------------------------------------------------------------------------------

#: Columns of padding on each side of the ring buffers (the count window reaches 9 to the right).
PAD = 10
#: Context models mixed: two direct tables, four hashed ones.
NM = 6
#: All twelve template cells (2 bits each) hold class q: q * UNIFORM.
UNIFORM = 0x555555


@njit(cache=True, inline="always")
def model_tables(
    direct: np.ndarray, hbits: int, quiet_contexts: int, mix1_rows: int, mix2_rows: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fresh state of a model (both kernels have the same layout, sized differently).

    Returns ``(off, t, vt, quiet, wts1, wts2, idx, sti)``: the counter offsets of the :data:`NM`
    models (``direct`` context counts of the direct ones, then hashed tables of ``2**hbits``) and
    their counters, the escape path's value counters, the quiet-cell counters, the two mixers'
    weight sets, and the scratch rows of context indices and stretched inputs (the bias input
    fixed at 256).
    """
    off = model_offsets(direct, NM - 2, hbits)
    t = np.full(off[NM], COUNTER_INIT, np.uint32)
    vt = np.full(VALUE_TABLE, COUNTER_INIT, np.uint32)
    quiet = np.full(quiet_contexts, COUNTER_INIT, np.uint32)
    wts1 = np.full((mix1_rows, NM + 1), W_INIT, np.int64)
    wts2 = np.full((mix2_rows, NM + 1), W_INIT, np.int64)
    idx = np.zeros(NM, np.int64)
    sti = np.zeros(NM + 1, np.int64)
    sti[NM] = 256
    return off, t, vt, quiet, wts1, wts2, idx, sti


@njit(cache=True, nogil=True)
def code_whole(
    dec: bool,
    data: np.ndarray,
    trinary: bool,
    src: np.ndarray,
    hbits: int,
    sq: np.ndarray,
    st: np.ndarray,
    rates: np.ndarray,
) -> tuple[np.ndarray, int]:
    """Encode ``data`` into a new buffer, or (``dec``) decode ``src`` into ``data``.

    The whole-map model codes every cell from the cells before it in raster order.

    A cell's class (unknown, free, occupied, or "other" for any value but -1, 0 and 100) is coded as
    at most three binary decisions: "same class as the cell to the west?", then "is it the first
    remaining class?", and so on. An "other" cell then codes its exact byte through an 8-level binary
    tree (the escape path), so any int8 grid round-trips.

    Each decision is predicted by six adaptive context models whose probabilities are mixed in the
    logistic domain by two small online-trained mixers (context mixing, as in PAQ); the choice of
    neighbours follows JBIG2's generic-region templates:

    ====  ===================================================================================
    m0    W, N, NW, NE (direct table)
    m1    m0 plus WW, NN, NWW, NEE (direct table)
    m2    m1 plus NNW, NNE, WWW, NNN (hashed)
    m3    m2 plus seven more cells up to four away (hashed)
    m4    W, N, NW, NE, distance to the next class change in the two rows above, run of W (hashed):
          where a sloping edge will cross this row
    m5    W, N and how many unknown, free and occupied cells lie in the 17x3 window above and the
          8 cells to the west (hashed): how "noisy" the neighbourhood is, which sets the odds of speckle
    ====  ===================================================================================

    Most cells of a map lie deep inside a uniform region. For a cell whose 12-cell template and whole
    count window hold one class (a "quiet" cell), one adaptive counter per class predicts "same again";
    only a surprise there goes on to the mixed models. This skips the mixing for two cells in three
    to nine in ten on the shared maps and about halves the time, at no cost in size.

    Neighbours outside the grid read as unknown. Encoder and decoder run the same function; ``dec``
    picks which side of the arithmetic coder it calls.

    ``trinary`` promises that every cell is -1, 0 or 100; ``hbits`` sizes the hashed tables.
    Returns ``(buffer, n)``: the encoder's bytes and their count, or for the decoder ``src`` and
    0 on success, -1 when the stream ran out or had bytes left over.
    """
    H, W = data.shape
    WP = W + 2 * PAD
    cls = np.zeros((4, WP), np.uint8)  # ring of class rows; outside the grid reads as unknown (0)
    nxt = np.zeros((4, WP), np.uint8)  # per row: distance to the next class change, capped at 15
    cnt3 = np.zeros((4, WP), np.int32)  # per column: class counts over the three rows above
    off, t, vt, quiet, wts1, wts2, idx, sti = model_tables(
        np.array([256, 65536], np.int64), hbits, 4, 4 * 256, 4 * 8192
    )
    win = np.zeros(4, np.int64)
    row_cnt = np.zeros(4, np.int64)
    cands = np.zeros(4, np.int64)
    x1, x2, x, buf, pos, end = start_coder(dec, src, max(4096, (H * W) // 32))

    for r in range(H):
        cur = cls[r & 3]
        r1 = cls[(r - 1) & 3]
        r2 = cls[(r - 2) & 3]
        r3 = cls[(r - 3) & 3]
        n1 = nxt[(r - 1) & 3]
        n2 = nxt[(r - 2) & 3]
        cur[:] = 0
        for q in range(4):
            row_cnt[q] = 0
            acc = 0
            for j in range(PAD - 9, PAD + 8):  # the loop slides in column c + 8 first
                acc += cnt3[q, j]
            win[q] = acc
        run = 0
        for c in range(W):
            p = c + PAD
            total = 0
            for q in range(4):
                win[q] += cnt3[q, p + 8] - cnt3[q, p - 9]
                total += win[q] + row_cnt[q]
            Wc = int(cur[p - 1])
            N = int(r1[p])
            c1 = Wc | (N << 2) | (int(r1[p - 1]) << 4) | (int(r1[p + 1]) << 6)
            c2 = c1 | (int(cur[p - 2]) << 8) | (int(r2[p]) << 10)
            c2 |= (int(r1[p - 2]) << 12) | (int(r1[p + 2]) << 14)
            c3 = c2 | (int(r2[p - 1]) << 16) | (int(r2[p + 1]) << 18)
            c3 |= (int(cur[p - 3]) << 20) | (int(r3[p]) << 22)

            s = 0
            v = 0
            if not dec:
                v = int(data[r, c])
                s = cell_class(v)
            first = 0
            if Wc != 3 and c3 == Wc * UNIFORM and win[Wc] + row_cnt[Wc] == total:
                # Quiet cell: one counter per class says "same again"; only a surprise goes on.
                y = 1 if s == Wc else 0
                y, x1, x2, x, buf, pos = code_quiet(dec, y, quiet, Wc, rates, x1, x2, x, buf, pos)
                first = -1 if y else 1
                s = Wc if y else s
            if first >= 0:
                c4 = c3 | (int(r2[p - 2]) << 24) | (int(r2[p + 2]) << 26)
                c4 |= (int(r1[p + 3]) << 28) | (int(r1[p - 3]) << 30)
                c4 |= (int(cur[p - 4]) << 32) | (int(r3[p - 1]) << 34) | (int(r3[p + 1]) << 36)
                c5 = c1 | (int(n1[p]) << 8) | (int(n2[p]) << 12) | (int(run) << 16)
                c6 = Wc | (N << 2) | (quant(win[0] + row_cnt[0]) << 4)
                c6 |= (quant(win[1] + row_cnt[1]) << 7) | (quant(win[2] + row_cnt[2]) << 10)
                idx[0] = off[0] + (c1 << 2)
                idx[1] = off[1] + (c2 << 2)
                idx[2] = off[2] + hashed(c3, 1, hbits)
                idx[3] = off[3] + hashed(c4, 2, hbits)
                idx[4] = off[4] + hashed(c5, 3, hbits)
                idx[5] = off[5] + hashed(c6, 4, hbits)
                # Decision k asks "is it cands[k]?"; the last candidate is implied.
                nc = candidates(Wc, -1, trinary, cands)
                k = first
                while k < nc - 1:
                    y = 1 if s == cands[k] else 0
                    y, x1, x2, x, buf, pos = mix_code(
                        dec, y, k, idx, t, wts1, k * 256 + c1, wts2, k * 8192 + c6, sti, sq, st, rates,
                        x1, x2, x, buf, pos,
                    )  # fmt: skip
                    if y:
                        break
                    k += 1
                s = cands[k]
            if s == 3:
                # Escape: the exact byte, predicted from a west or north neighbour's "other" value.
                pv = neighbour_byte(data, r, c, Wc, N)
                v, x1, x2, x, buf, pos = code_escape(dec, v, pv, vt, rates, x1, x2, x, buf, pos)
            elif dec:
                v = class_value(s)
            if dec:
                if pos > end:
                    return buf, -1
                data[r, c] = v
            run = min(run + 1, 15) if (c > 0 and s == Wc) else 0
            cur[p] = s
            row_cnt[s] += 1
            if c >= 8:
                row_cnt[cur[p - 8]] -= 1
        # End of row: column counts drop row r - 3 and add row r; change distances of row r.
        for j in range(PAD, PAD + W):
            if r >= 3:
                cnt3[r3[j], j] -= 1
            cnt3[cur[j], j] += 1
        nn = nxt[r & 3]
        nn[PAD + W - 1] = 15
        for j in range(PAD + W - 2, PAD - 1, -1):
            nn[j] = 1 if cur[j] != cur[j + 1] else min(nn[j + 1] + 1, 15)
    return finish_coder(dec, x1, x2, buf, pos, end)


# ----------------------------------------------------------------------------------------------------
# The delta model
# ----------------------------------------------------------------------------------------------------

#: Class code for "outside the base" (read as unknown, but the models keep it apart).
OUTSIDE = 4


@njit(cache=True, inline="always")
def fill_base_row(
    base: np.ndarray, rb: int, off_c: int, W: int, classes: np.ndarray, values: np.ndarray
) -> None:
    """Base row ``rb`` aligned on the new grid's columns: classes (OUTSIDE where the base has no
    cell) into ``classes[PAD:PAD + W]``, and values (-1 outside) into ``values[:W]``."""
    classes[:] = OUTSIDE
    values[:] = -1
    Hb, Wb = base.shape
    if rb < 0 or rb >= Hb:
        return
    c0 = max(0, -off_c)
    c1 = min(W, Wb - off_c)
    for c in range(c0, c1):
        v = int(base[rb, c + off_c])
        values[c] = v
        classes[PAD + c] = cell_class(v)


@njit(cache=True, nogil=True)
def code_delta(
    dec: bool,
    data: np.ndarray,
    base: np.ndarray,
    off_r: int,
    off_c: int,
    trinary: bool,
    src: np.ndarray,
    hbits: int,
    sq: np.ndarray,
    st: np.ndarray,
    rates: np.ndarray,
) -> tuple[np.ndarray, int]:
    """Encode ``data`` against ``base`` into a new buffer, or (``dec``) decode ``src`` into ``data``.

    The delta model codes a new map version against a base version both ends hold.

    The base is aligned with the new grid by a whole-cell offset (cell ``(r, c)`` of the new grid lies
    on cell ``(r + off_r, c + off_c)`` of the base); new cells outside the base read as unknown, which
    is what the base said about them. Each cell then answers "same value as the base cell?" first; only
    a changed cell goes on to code its class (among the classes other than the base's) and, for values
    other than -1, 0 and 100, its exact byte, as in the whole-map model.

    Changes between map versions come in clusters near the robot and along the old frontier, so the
    models look at the base around the cell (including the cells below and to the right, which the
    decoder also has), at which causal neighbours changed, and at the new classes around the cell:

    ====  ===================================================================================
    m0    base class, whether W and N changed, W, N (direct)
    m1    base class, which of W, N, NW, NE changed, W, N, NW, NE (direct)
    m2    base class and its four base neighbours, whether W and N changed, W, N (hashed)
    m3    base class, W, N, NW, NE, WW, NN and which of them changed (hashed)
    m4    base class, changes counted in the 17x3 window above and 8 cells to the west, whether W and
          N changed, W, N, base S and E (hashed)
    m5    the base's 3x3 block, whether W and N changed, W (hashed)
    ====  ===================================================================================

    A cell with no change anywhere in its count window (a "quiet" cell, most of any delta) is coded
    with one adaptive counter per base class and "base 3x3 uniform" flag instead of the mixed models.

    Returns ``(buffer, n)`` like :func:`code_whole`.
    """
    H, W = data.shape
    WP = W + 2 * PAD
    cls = np.zeros((4, WP), np.uint8)  # new classes, ring of rows (outside: unknown)
    chg = np.zeros((4, WP), np.uint8)  # 1 where the new value differs from the base's
    bcl = np.full((4, WP), OUTSIDE, np.uint8)  # aligned base classes, rows r - 1, r, r + 1
    bvl = np.full((4, W), -1, np.int64)  # aligned base values, same rows
    ccol = np.zeros(WP, np.int32)  # per column: changes over the three rows above
    off, t, vt, quiet, wts1, wts2, idx, sti = model_tables(
        np.array([512, 32768], np.int64), hbits, 16, 4 * 128, 4 * 1024
    )
    cands = np.zeros(4, np.int64)
    x1, x2, x, buf, pos, end = start_coder(dec, src, max(4096, (H * W) // 256))

    fill_base_row(base, off_r - 1, off_c, W, bcl[3], bvl[3])
    fill_base_row(base, off_r, off_c, W, bcl[0], bvl[0])
    for r in range(H):
        cur = cls[r & 3]
        r1 = cls[(r - 1) & 3]
        r2 = cls[(r - 2) & 3]
        ch = chg[r & 3]
        ch1 = chg[(r - 1) & 3]
        ch2 = chg[(r - 2) & 3]
        ch3 = chg[(r - 3) & 3]
        bn = bcl[(r - 1) & 3]
        b0 = bcl[r & 3]
        bs = bcl[(r + 1) & 3]
        bval = bvl[r & 3]
        fill_base_row(base, r + 1 + off_r, off_c, W, bs, bvl[(r + 1) & 3])
        cur[:] = 0
        ch[:] = 0
        cwin = 0
        for j in range(PAD - 9, PAD + 8):
            cwin += ccol[j]
        crow = 0
        for c in range(W):
            p = c + PAD
            cwin += ccol[p + 8] - ccol[p - 9]
            B = int(b0[p])
            bv = bval[c]
            cW = int(ch[p - 1])
            cN = int(ch1[p])
            s = 0
            v = 0
            if not dec:
                v = int(data[r, c])
                s = cell_class(v)
            Bk = B if B != OUTSIDE else 0  # the class the base stands for
            bu = 1 if (bn[p] == B and bs[p] == B and b0[p - 1] == B and b0[p + 1] == B) else 0
            k = 0  # decision 0: unchanged?
            if cwin + crow == 0:
                y = 1 if v == bv else 0
                y, x1, x2, x, buf, pos = code_quiet(dec, y, quiet, B * 2 + bu, rates, x1, x2, x, buf, pos)
                k = -1 if y else 1
            Wc = int(cur[p - 1])
            N = int(r1[p])
            if k >= 0:
                NW = int(r1[p - 1])
                NE = int(r1[p + 1])
                cNW = int(ch1[p - 1])
                cNE = int(ch1[p + 1])
                cc = cW | (cN << 1)
                d0 = B | (cc << 3) | (Wc << 5) | (N << 7)
                d1 = d0 | (cNW << 9) | (cNE << 10) | (NW << 11) | (NE << 13)
                d2 = d0 | (int(bn[p]) << 9) | (int(bs[p]) << 12) | (int(b0[p - 1]) << 15)
                d2 |= int(b0[p + 1]) << 18
                d3 = d1 | (int(cur[p - 2]) << 15) | (int(r2[p]) << 17)
                d3 |= (int(ch[p - 2]) << 19) | (int(ch2[p]) << 20) | (int(bs[p]) << 21)
                qc = quant(cwin + crow)
                d4 = d0 | (qc << 9) | (int(bs[p]) << 12) | (int(b0[p + 1]) << 15)
                d5 = B | (cc << 3) | (Wc << 5) | (int(bn[p - 1]) << 7) | (int(bn[p]) << 10)
                d5 |= (int(bn[p + 1]) << 13) | (int(b0[p - 1]) << 16) | (int(b0[p + 1]) << 19)
                d5 |= (int(bs[p - 1]) << 22) | (int(bs[p]) << 25) | (int(bs[p + 1]) << 28)
                idx[0] = off[0] + (d0 << 2)
                idx[1] = off[1] + (d1 << 2)
                idx[2] = off[2] + hashed(d2, 11, hbits)
                idx[3] = off[3] + hashed(d3, 12, hbits)
                idx[4] = off[4] + hashed(d4, 13, hbits)
                idx[5] = off[5] + hashed(d5, 14, hbits)
                ws1 = B | (cc << 3) | (bu << 5)
                ws2 = qc | (Wc << 3) | (N << 5) | (bu << 7)
                if k == 0:
                    y = 1 if v == bv else 0
                    y, x1, x2, x, buf, pos = mix_code(
                        dec, y, 0, idx, t, wts1, ws1, wts2, ws2, sti, sq, st, rates, x1, x2, x, buf, pos
                    )
                    k = -1 if y else 1
                if k >= 1:
                    # Changed: its class, among those other than the base's (any, if "other").
                    nc = candidates(-1, Bk if Bk != 3 else -1, trinary, cands)
                    j = 0
                    while j < nc - 1:
                        y = 1 if s == cands[j] else 0
                        y, x1, x2, x, buf, pos = mix_code(
                            dec, y, j + 1, idx, t, wts1, (j + 1) * 128 + ws1, wts2, (j + 1) * 1024 + ws2,
                            sti, sq, st, rates, x1, x2, x, buf, pos,
                        )  # fmt: skip
                        if y:
                            break
                        j += 1
                    s = cands[j]
            if k < 0:
                s = cell_class(bv)
                if dec:
                    v = bv
            elif s == 3:
                # The base's own "other" value predicts best; else a neighbour's, as in the whole map.
                pv = (bv & 255) if B == 3 else neighbour_byte(data, r, c, Wc, N)
                v, x1, x2, x, buf, pos = code_escape(dec, v, pv, vt, rates, x1, x2, x, buf, pos)
            elif dec:
                v = class_value(s)
            if dec:
                if pos > end:
                    return buf, -1
                data[r, c] = v
            changed = 0 if k < 0 else 1
            cur[p] = s
            ch[p] = changed
            crow += changed
            if c >= 8:
                crow -= ch[p - 8]
        for j in range(PAD, PAD + W):
            ccol[j] += np.int32(ch[j]) - (np.int32(ch3[j]) if r >= 3 else 0)
    return finish_coder(dec, x1, x2, buf, pos, end)
