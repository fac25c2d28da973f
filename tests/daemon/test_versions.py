"""Versions as (incarnation, number): newer is larger, a lost disk starts a larger incarnation."""

from __future__ import annotations

import pytest

from mapd.daemon.versions import EPOCH, NUMBER_MASK, incarnation_at, label, make, next_version, split


def test_round_trip_order_and_labels() -> None:
    v = make(1234, 56)
    assert split(v) == (1234, 56) and label(v) == "v56" and label(None) == "-"
    assert make(1234, NUMBER_MASK) < make(1235, 1)  # every later incarnation is newer
    with pytest.raises(ValueError):
        make(-1, 1)


def test_a_fresh_state_starts_an_incarnation_from_the_clock() -> None:
    t = EPOCH + 500.0
    first = next_version(0, t)
    assert split(first) == (500, 1) and split(next_version(first, t + 99)) == (500, 2)
    # the same robot after losing its disk a minute later: larger than anything it sent before
    assert next_version(0, t + 60) > make(500, 10_000)


def test_legacy_counters_keep_counting_and_a_full_incarnation_rolls_over() -> None:
    assert next_version(41, EPOCH + 10.0) == 42  # a state dir from before incarnations (incarnation 0)
    full = make(7, NUMBER_MASK)
    nxt = next_version(full, EPOCH + 3.0)
    assert nxt > full and split(nxt) == (8, 1)
    assert incarnation_at(0.0) == 1  # a clock before the epoch still gives a valid incarnation
