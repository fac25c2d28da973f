"""Signed, fresh keyframe requests (transports/signed_requests.py), shared by uwb and zenoh."""

from __future__ import annotations

import pytest

from mapd.errors import SignatureError
from mapd.identity import Identity, Roster
from transports import signed_requests
from transports.uwb import keyframe_requests as uwb_requests
from transports.zenoh import queries as zenoh_queries

IDS = {n: Identity.generate(n) for n in ("a", "b")}
ROSTER = Roster({n: i.public_key for n, i in IDS.items()})


def _verify(
    domain: bytes, sig: bytes, *, fleet: str = "f", robots: tuple[str, ...] = ("a",), nonce: int = 7
) -> None:
    signed_requests.verify(
        ROSTER, domain, fleet=fleet, asker="b", robots=list(robots), nonce=nonce, sig=sig, what="request"
    )


def test_a_zenoh_querys_signature_does_not_pass_as_a_uwb_request() -> None:
    """The two transports sign under their own domains: one captured on the Wi-Fi side cannot be
    played back over the radio, where the same fleet, asker, robot and nonce would be asked."""
    sig = signed_requests.sign(IDS["b"], zenoh_queries.DOMAIN, fleet="f", asker="b", robots=["a"], nonce=7)
    _verify(zenoh_queries.DOMAIN, sig)
    with pytest.raises(SignatureError):
        _verify(uwb_requests.DOMAIN, sig)
    # Nor for another robot asked, nonce or fleet.
    for bad in ({"robots": ("b",)}, {"robots": ("a", "b")}, {"nonce": 8}, {"fleet": "g"}):
        with pytest.raises(SignatureError):
            _verify(zenoh_queries.DOMAIN, sig, **bad)  # type: ignore[arg-type]


def test_freshness_heeds_each_asker_once_per_nonce_and_stays_bounded() -> None:
    f = signed_requests.Freshness(max_askers=2)
    assert f.fresh("a", 5) and not f.fresh("a", 5) and not f.fresh("a", 4) and f.fresh("a", 6)
    assert f.fresh("b", 1) and f.fresh("c", 1)  # three askers: a, heard longest ago, is forgotten
    assert len(f._last) == 2 and f.fresh("a", 6)  # so one old request of a's passes once more
    assert not f.fresh("c", 1)  # c is still remembered
