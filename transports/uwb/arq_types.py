"""What the UWB ARQ core takes and gives: its config, its events and its counters.

Plain data, kept apart from the rules in :mod:`transports.uwb.arq` (which re-exports every name
here, so callers keep writing ``arq.ArqConfig`` and ``arq.MessageReceived``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from transports.uwb import wire
from transports.uwb.pacing import MacMode

#: How receivers acknowledge (R13, R16): ``each`` acks every message as it arrives (selective acks
#: every ``ack_every`` chunks or ``ack_delay_s``); ``nack`` acks only gaps and completion, for every
#: message; ``auto`` is ``nack`` for broadcast messages (more than one intended peer) and ``each``
#: for unicast ones. Every node on a channel should use the same setting.
AckMode = Literal["auto", "each", "nack"]
ACK_MODES: tuple[AckMode, ...] = ("auto", "each", "nack")


@dataclass(frozen=True)
class ArqConfig:
    """Settings of one endpoint (the adapter builds it from the transport's options).

    Out-of-range values are the caller's mistake and raise ValueError: adapters check user options
    first and turn them into one-line config errors.
    """

    node_id: int
    max_frame: int = 224
    rate_bps: float = 12500.0
    max_message_bytes: int = 8 << 20
    window: int = 128
    #: A message's deadline, unless the caller gives one: at least this, longer for a message
    #: longer on the air at the node's share of the channel (R6: ``ArqEndpoint.message_deadline_s``).
    deadline_s: float = 120.0
    initial_rto_s: float = 1.0
    min_rto_s: float = 0.3
    max_rto_s: float = 4.0
    ack_delay_s: float = 0.0  # 0: four max-size frame times at rate_bps
    ack_every: int = 8
    ack_min_gap_s: float = 0.05
    acks: AckMode = "auto"
    #: NACK mode: the longest random wait before a gap report (0: eight times ack_delay_s, 32
    #: frame times: long enough that one report carries several gaps and others can overhear it).
    nack_backoff_s: float = 0.0
    reorder_tolerance: int = 3
    beacon_s: float = 5.0
    peer_timeout_s: float = 20.0
    max_peers: int = 64
    max_partials_per_peer: int = 4
    rx_budget_bytes: int = 0  # 0: two of the largest messages, chunks counted with CHUNK_COST
    partial_ttl_s: float = 0.0  # 0: twice deadline_s
    mac: MacMode = "none"
    slot_s: float = 0.25
    slots: int = 1
    slot_index: int = 0
    guard_s: float = 0.01
    clock_offset: float = 0.0
    #: TDMA: keep the turns on a clock agreed over the radio (``radio_time.py``) while the wall
    #: clocks are not all kept by a time service; off: on the wall clock alone.
    radio_time: bool = False
    #: TDMA: how late a frame's bytes may reach this node after the frame's end on the air (the
    #: radio's serial line, at the port's baud): R18 counts a frame out of turn only when it was
    #: certainly on the air in this node's own slot.
    rx_slack_s: float = 0.025
    sense_s: float = 0.02
    backoff_min_s: float = 0.0
    backoff_max_s: float = 0.1
    #: TDMA: lend the rest of an own slot with nothing left in it to the peer heard with the most
    #: chunks still to send (R17).
    lend: bool = False
    #: NACK mode: repair with parity chunks (``fec.py``), each of use to every receiver lacking any
    #: chunk of its block, instead of resending the chunks asked for (R16). Every node on the
    #: channel must understand parity (wire.py).
    fec: bool = False
    key: bytes | None = field(default=None, repr=False)
    counter_start: int = 0
    #: Sender id -> the highest signed counter accepted from it before a restart (never again).
    replay_marks: dict[int, int] = field(default_factory=dict, repr=False)
    #: Refuse signed frames whose counter runs ahead of this node's wall clock (``now`` plus
    #: ``clock_offset``); off for simulations whose clock is not the wall clock.
    check_counter_clock: bool = False

    def __post_init__(self) -> None:
        if not 1 <= self.node_id <= 254:
            raise ValueError(f"uwb: node id {self.node_id} is not in 1..254")
        if not 1 <= self.window <= 8 * wire.MAX_BITMAP:
            raise ValueError(f"uwb: window {self.window} is not in 1..{8 * wire.MAX_BITMAP}")
        if self.acks not in ACK_MODES:
            raise ValueError(f"uwb: acks {self.acks!r} is not one of {', '.join(ACK_MODES)}")


# --- events -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MessageReceived:
    """A whole message from ``src`` passed its length and hash checks (delivered once)."""

    src: int
    stream: int
    msg: int
    data: bytes


@dataclass(frozen=True)
class MessageDelivered:
    """``peer`` acked our message ``msg`` as complete."""

    msg: int
    peer: int


@dataclass(frozen=True)
class MessageFailed:
    """Our message ``msg`` will not reach ``peer`` (deadline, or the peer refused it). ``final``:
    the peer refused it (over its message limit), and would refuse the same message again."""

    msg: int
    peer: int
    reason: str
    final: bool = False


@dataclass(frozen=True)
class MessageFlushed:
    """Every chunk of our reliable message ``msg`` has been on the air once (R5): receivers may now
    complete it, and what is left is repair."""

    msg: int


@dataclass(frozen=True)
class MessageClosed:
    """A message left the send queue: ``delivered`` (to all), ``failed`` (some) or ``superseded``."""

    msg: int
    outcome: str


@dataclass(frozen=True)
class PeerUp:
    """A peer was heard for the first time, or again after it was down."""

    peer: int


@dataclass(frozen=True)
class PeerDown:
    """A peer was silent for ``peer_timeout_s``."""

    peer: int


@dataclass(frozen=True)
class PeerRestarted:
    """A peer came back with a new session id (it forgot what it held)."""

    peer: int


@dataclass(frozen=True)
class PeerFeatures:
    """A peer's HELLO announced ``features`` (``wire.F_*`` bits; 0: a node from before the
    announcement) that lack some this node understands, or, after such, all of them. Parity, DONE
    and LENDs go to it only if it understands them (wire.py, *Features*)."""

    peer: int
    features: int


Event = (
    MessageReceived
    | MessageDelivered
    | MessageFailed
    | MessageFlushed
    | MessageClosed
    | PeerUp
    | PeerDown
    | PeerRestarted
    | PeerFeatures
)


# --- counters -----------------------------------------------------------------------------------


@dataclass
class ArqCounters:
    """What an endpoint has counted. ``stats()`` reports each field under its name, in this order
    (``mapd status`` and ``mapd link`` show them), so a rename here changes what users see."""

    # traffic
    bytes_tx: int = 0
    bytes_rx: int = 0
    frames_tx: int = 0
    frames_rx: int = 0
    data_tx: int = 0
    resends: int = 0
    acks_tx: int = 0
    acks_rx: int = 0
    #: NACK mode (R16): gap reports sent, and those dropped because another receiver's overheard
    #: ACK had already asked for every chunk this node lacks.
    nacks_tx: int = 0
    nacks_suppressed: int = 0
    #: COMPLETEs sent in DONE frames (each DONE frame also counts once in acks_tx).
    completes_tx: int = 0
    #: Chunks queued for resend at a NACK's request (one resend serves every receiver lacking it).
    repairs_queued: int = 0
    hellos_tx: int = 0
    #: TIME frames sent and heard (the fleet's radio clock, ``radio_time.py``).
    times_tx: int = 0
    times_rx: int = 0
    #: LEND frames sent (own slots' rests lent), and slots' rests borrowed on a peer's LEND (R17).
    lends_tx: int = 0
    borrowed: int = 0
    #: Parity chunks sent and received (held), and chunks rebuilt from parity (fec.py).
    parity_tx: int = 0
    parity_rx: int = 0
    recovered: int = 0
    timeouts: int = 0
    # frames and chunks dropped, by cause
    bad_frames: int = 0
    #: Signed frames reaching a node without the link key (a fleet configured half signed).
    signed_no_key: int = 0
    duplicates: int = 0
    stale: int = 0
    stale_session: int = 0
    not_for_me: int = 0
    own_id: int = 0
    rejected: int = 0
    hash_errors: int = 0
    #: TDMA (R18): frames of others certainly on the air in this node's own slot (clocks disagree,
    #: or two robots were given one slot).
    out_of_turn: int = 0
    evicted: int = 0
    superseded: int = 0
    #: COMPLETEs heard for a message after a newer one on its stream superseded it (still delivered).
    late_completes: int = 0
    superseded_rx: int = 0
    unknown_acks: int = 0
    stale_acks: int = 0
    gen_resets: int = 0
    peers_full: int = 0
    # messages
    messages_tx: int = 0
    messages_delivered: int = 0
    messages_failed: int = 0
    messages_rx: int = 0
    bytes_delivered: int = 0
