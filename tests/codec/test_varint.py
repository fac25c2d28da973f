"""The LEB128 varints under the Huffman stage's run count and lossless's delta offsets."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapd.codec.varint import VarintErrors, get_uvarint, put_uvarint, unzigzag, zigzag
from mapd.errors import CodecError

ERR = VarintErrors(truncated="cut short", non_minimal="not minimal", overlong="too long")


def test_known_encodings() -> None:
    assert put_uvarint(0) == b"\x00"
    assert put_uvarint(127) == b"\x7f"
    assert put_uvarint(128) == b"\x80\x01"
    assert put_uvarint(300) == b"\xac\x02"
    assert [zigzag(n) for n in (0, -1, 1, -2, 2)] == [0, 1, 2, 3, 4]


@given(st.integers(0, 2**35 - 1), st.binary(max_size=3))
def test_roundtrip(value: int, prefix: bytes) -> None:
    buf = prefix + put_uvarint(value) + b"\xff"
    assert get_uvarint(buf, len(prefix), 5, ERR) == (value, len(buf) - 1)


@given(st.integers(-(2**31), 2**31))
def test_zigzag_roundtrip(n: int) -> None:
    assert unzigzag(zigzag(n)) == n and zigzag(n) >= 0


@pytest.mark.parametrize(
    ("buf", "message"),
    [
        (b"", "cut short"),
        (b"\x80", "cut short"),
        (b"\x80\x00", "not minimal"),
        (b"\xff" * 5 + b"\x01", "too long"),
    ],
)
def test_bad_forms_name_the_callers_field(buf: bytes, message: str) -> None:
    with pytest.raises(CodecError, match=message):
        get_uvarint(buf, 0, 5, ERR)
