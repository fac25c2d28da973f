"""Properties of the compiled kernels that the codec's safety rests on."""

from __future__ import annotations

import ast
import inspect

import numpy as np
from numba.core.registry import CPUDispatcher

from mapd.codec import ctx_kernels as K


def test_every_compiled_function_lives_in_the_kernel_module() -> None:
    # numba's cache watches only the defining file; a compiled helper imported from elsewhere could
    # leave stale kernels behind after an edit (see the ctx_kernels docstring).
    tree = ast.parse(inspect.getsource(K))
    imported = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert all(not (n.module or "").startswith("mapd") for n in imported)
    compiled = [v for v in vars(K).values() if isinstance(v, CPUDispatcher)]
    assert {"code_whole", "code_delta", "mix_code", "encode_bit", "decode_bit"} <= {
        f.py_func.__name__ for f in compiled
    }
    for f in compiled:
        assert f.py_func.__module__ == K.__name__
        for name in f.py_func.__code__.co_names:
            target = getattr(K, name, None)
            if isinstance(target, CPUDispatcher):
                assert target.py_func.__module__ == K.__name__, (f.py_func.__name__, name)


def test_logistic_tables_are_monotone_inverses() -> None:
    sq, st = K.build_tables()
    assert sq.shape == (2 * K.XMAX + 1,) and st.shape == (65536,)
    assert np.all(np.diff(sq) >= 0) and sq[0] >= 1 and sq[-1] <= 65535
    assert sq[K.XMAX] == 32768  # logit 0 is one half
    assert np.all(np.diff(st.astype(np.int64)) >= 0)
    # stretch then squash lands at or above the probability it started from, never far off
    p = np.arange(1, 65536, 97)
    back = sq[st[p].astype(np.int64) + K.XMAX]
    assert np.all(back >= p) and np.all(back - p <= 1 + p // 40)


def test_hashed_tables_grow_with_the_grid_within_bounds() -> None:
    assert K.hash_bits(1) == K.HASH_BITS_MIN
    assert K.hash_bits(1 << 26) == K.HASH_BITS_MAX
    sizes = [K.hash_bits(n) for n in (10**3, 10**4, 10**5, 10**6)]
    assert sizes == sorted(sizes) and len(set(sizes)) > 2


def test_arithmetic_coder_round_trips_skewed_bits() -> None:
    # The codec in miniature: a constant-probability stream of 20 000 bits through both kernels'
    # coder, at probabilities from near-certain to even.
    rng = np.random.default_rng(5)
    for p1 in (1, 300, 32768, 65000, 65535):
        bits = (rng.random(20_000) < p1 / 65536).astype(np.int64)
        buf, n = _encode_bits(bits, p1)
        out, status = _decode_bits(buf[:n].copy(), len(bits), p1)
        assert status == 0 and np.array_equal(out, bits), p1


def _encode_bits(bits: np.ndarray, p: int) -> tuple[np.ndarray, int]:
    buf = np.empty(16, np.uint8)  # small on purpose: the encoder must grow it
    x1, x2, pos = 0, 0xFFFFFFFF, 0
    for y in bits:
        x1, x2, buf, pos = K.encode_bit(int(y), p, x1, x2, buf, pos)
    return K.flush_encoder(x1, x2, buf, pos)


def _decode_bits(buf: np.ndarray, n: int, p: int) -> tuple[np.ndarray, int]:
    x, pos = K.start_decoder(buf)
    x1, x2 = 0, 0xFFFFFFFF
    out = np.zeros(n, np.int64)
    for i in range(n):
        out[i], x1, x2, x, pos = K.decode_bit(p, x1, x2, x, buf, pos)
    return out, 0 if pos == buf.shape[0] + K.OVERREAD else -1


def test_bitstream_is_pinned_to_the_model_version() -> None:
    # If this fails, the model's output changed: bump MODEL_VERSION in ctx_kernels.py (so robots on
    # different versions refuse each other's payloads clearly), then update the digests here and
    # rebuild tests/codec/corpus_lossless with its make_corpus.py.
    import hashlib

    from mapd.codec import encode, read_header
    from mapd.mapping.synthetic import room_grid

    base = room_grid(seed=0).replace(version=1)
    d = base.data.copy()
    d[10:20, 10:20] = 0
    odd = base.data.copy()
    odd[5, 5:9] = (42, -7, 100, 3)
    new = base.replace(data=d, version=2)
    got = []
    for payload in (
        encode(base, "lossless"),
        encode(new, "lossless", base=base),
        encode(base.replace(data=odd), "lossless"),
    ):
        body = payload[read_header(payload).body_offset :]
        assert body[0] >> 3 == K.MODEL_VERSION
        got.append(hashlib.sha256(body).hexdigest()[:16])
    assert K.MODEL_VERSION == 1
    assert got == ["b49a037d51c25236", "73ccc3ea478740be", "2d488d9dae343350"]
