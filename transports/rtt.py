"""Round-trip time and retransmission timeout, as RFC 6298 computes them for TCP.

Shared by the first-party transports: UWB times its chunk retransmissions with it, zenoh only
reports the smoothed offer-to-ack time.
"""

from __future__ import annotations


class RttEstimator:
    """Smoothed RTT, its variation, and an RTO that doubles on every timeout until a new sample."""

    def __init__(self, *, initial_rto: float = 1.0, min_rto: float = 0.3, max_rto: float = 4.0) -> None:
        self.min_rto = min_rto
        self.max_rto = max_rto
        self.srtt: float | None = None
        self.rttvar = 0.0
        self.rto = min(max(initial_rto, min_rto), max_rto)
        self.samples = 0
        self.last: float | None = None

    def sample(self, r: float) -> None:
        """A measured round trip (Karn: only from chunks sent once)."""
        r = max(0.0, r)
        self.last = r
        self.samples += 1
        if self.srtt is None:
            self.srtt, self.rttvar = r, r / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - r)
            self.srtt = 0.875 * self.srtt + 0.125 * r
        self.rto = min(max(self.srtt + max(0.01, 4 * self.rttvar), self.min_rto), self.max_rto)

    def backoff(self) -> None:
        """A timeout fired: wait twice as long next time (up to ``max_rto``)."""
        self.rto = min(self.rto * 2, self.max_rto)
