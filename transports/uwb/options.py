"""The ``[transports.uwb]`` options: the link, medium access, peers, limits and the relay, checked
when the config loads (one :class:`~mapd.errors.ConfigError` line for a bad value)."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from mapd.errors import ConfigError
from mapd.files.folders import from_workdir
from transports.base import TransportOptions
from transports.uwb.framing import MIN_FRAME
from transports.uwb.pacing import SLOT_FRAMES
from transports.uwb.sending import HASH_LEN
from transports.uwb.wire import MAX_TOTAL

#: The largest map a uwb link carries: what a DATA frame's 24-bit size field describes.
MAX_MESSAGE = MAX_TOTAL - HASH_LEN
#: The shortest timer a setting may give (s): a frame takes milliseconds on the air, and a timer of
#: 1e-300 s made the link's loop spin, firing on every pass.
MIN_TIMER_S = 0.01


class UwbOptions(TransportOptions):
    """The ``[transports.uwb]`` table."""

    port: str = Field(default="/dev/ttyUSB0", description="serial device of the UWB radio")
    baud: int = Field(default=115200, ge=1200, le=4_000_000, description="serial baud rate")
    link_rate_bps: int = Field(
        default=12500, ge=2000, le=10_000_000, description="bits/s this node may write (any 1 s window)"
    )
    max_frame: int = Field(default=224, ge=MIN_FRAME, le=4096, description="largest frame on the wire, bytes")
    node_id: int | None = Field(
        default=None, ge=1, le=254, description="this robot's link id; default nodes[robot]"
    )
    nodes: dict[str, int] = Field(
        default_factory=dict, description="robot name -> link id (1..254) on this channel"
    )
    peers: list[str] = Field(
        default_factory=list, description="robots that must ack each map; default: every other robot in nodes"
    )
    send_to: Literal["configured", "heard"] = Field(
        default="configured",
        description="whom each map goes to: every robot in peers (kept trying until deadline_s, also "
        "out of range), or those of them heard within peer_timeout_s (fleets spread over a building: "
        "the others get it by relay; mapd bench swarm --acks up)",
    )
    deadline_s: float = Field(
        default=120.0,
        ge=MIN_TIMER_S,
        description="give up on a map after this long, or after twice its time on the air at this "
        "robot's share of the link (link_rate_bps over the slots) if longer",
    )
    max_message_bytes: int | None = Field(
        default=None,
        ge=1024,
        le=MAX_MESSAGE,
        description="default: limits.max_message_bytes, at most 16 MiB (three hours at 12.5 kb/s)",
    )
    window: int = Field(default=128, ge=1, le=256, description="chunks in flight past the receiver's base")
    acks: Literal["auto", "each", "nack"] = Field(
        default="auto",
        description="how receivers ack: auto (gap reports and one COMPLETE for broadcast maps, "
        "selective acks for unicast), each (selective acks always), nack (gap reports always)",
    )
    pose_period_s: float = Field(
        default=5.0, ge=0.0, description="seconds between pose messages; they yield to maps (0: send none)"
    )
    fec: bool = Field(
        default=True,
        description="broadcast maps (acks auto/nack) are repaired with parity chunks, each of use to "
        "every robot lacking any chunk of its block; not to robots whose mapd announces it lacks "
        "them; a fleet with robots from before parity sets false (repairs resend the chunks asked for)",
    )
    mac: Literal["none", "tdma", "backoff"] = Field(
        default="none", description="medium access on a shared channel"
    )
    slot_ms: float | None = Field(
        default=None,
        gt=0,
        description=f"tdma: slot length; default {SLOT_FRAMES} max_frame frames at link_rate_bps plus guard_ms",
    )
    lend: bool = Field(
        default=True,
        description="tdma: lend the rest of an own slot with nothing left in it to the robot heard "
        "with the most chunks still to send (one sender per slot still)",
    )
    slots: int | None = Field(
        default=None, ge=1, le=254, description="tdma: slots per cycle; default len(nodes)"
    )
    slot_index: int | None = Field(default=None, ge=0, description="tdma: own slot; default rank of node_id")
    guard_ms: float = Field(default=10.0, ge=0, description="tdma: quiet time at the end of a slot")
    clock: Literal["radio", "system"] = Field(
        default="radio",
        description="tdma: the clock the turns are counted on. radio: the wall clock where a time "
        "service keeps it (chrony), else one the fleet agrees over the radio, led by a robot whose "
        "clock a time service keeps, or the lowest link id (no TIME frame is sent while every "
        "robot heard has a time service). system: the wall clock always (every robot must run chrony)",
    )
    rx_latency_ms: float | None = Field(
        default=None,
        ge=0,
        le=10_000,
        description="tdma: longest time from a frame's end on the air to its last byte at the port; "
        "default 10 bits a byte of max_frame at baud plus 5 ms. Frames of others heard in this "
        "robot's own slot are counted (out_of_turn) only past it: raise it if a radio that buffers "
        "makes out_of_turn count while the clocks agree",
    )
    sense_ms: float = Field(default=20.0, ge=0, description="backoff: channel idle time before a backoff")
    backoff_min_ms: float = Field(default=0.0, ge=0, description="backoff: shortest random wait")
    backoff_max_ms: float = Field(default=100.0, ge=0, description="backoff: longest random wait")
    beacon_s: float = Field(default=5.0, ge=MIN_TIMER_S, description="HELLO after this long without sending")
    peer_timeout_s: float = Field(
        default=20.0,
        ge=MIN_TIMER_S,
        description="a peer silent this long is down (tdma: at least beacon_s and two cycles, as a "
        "peer speaks only in its own slot)",
    )
    reopen_s: float = Field(
        default=1.0, ge=MIN_TIMER_S, description="retry a vanished serial port this often"
    )
    keyframe_request_s: float = Field(
        default=5.0, ge=MIN_TIMER_S, description="ask a robot for a whole map at most this often"
    )
    relay: bool = Field(
        default=True,
        description="forward peers' signed maps to neighbours that lack them and do not hear their "
        "robot (multi-hop; signed fleets only)",
    )
    # The timers mapd bench swarm measured (its tables in the README run with these defaults).
    summary_period_s: float = Field(
        default=10.0,
        ge=MIN_TIMER_S,
        description="relay: broadcast which versions this robot holds this often",
    )
    relay_period_s: float = Field(
        default=2.0, ge=MIN_TIMER_S, description="relay: start at most one relay this often"
    )

    @model_validator(mode="after")
    def _check(self) -> UwbOptions:
        for name, i in self.nodes.items():
            if not 1 <= i <= 254:
                raise ValueError(f"nodes.{name}: link id {i} is not in 1..254")
        if len(set(self.nodes.values())) != len(self.nodes):
            raise ValueError("nodes: two robots share a link id")
        if self.link_rate_bps / 8 < 2 * self.max_frame:
            # the pacer's burst is two frames (a data frame and an ack back to back)
            raise ValueError(
                f"link_rate_bps {self.link_rate_bps} cannot carry two {self.max_frame}-byte frames a second"
            )
        if self.backoff_max_ms < self.backoff_min_ms:
            raise ValueError("backoff_max_ms is below backoff_min_ms")
        if (
            self.mac == "tdma"
            and self.max_frame * 8 / self.link_rate_bps > (self.slot_length_ms - self.guard_ms) / 1000
        ):
            raise ValueError("tdma: a max_frame frame does not fit in slot_ms - guard_ms at link_rate_bps")
        return self

    @property
    def rx_latency_s(self) -> float:
        """``rx_latency_ms`` in seconds, or by default a max_frame frame's time on the serial line."""
        if self.rx_latency_ms is not None:
            return self.rx_latency_ms / 1000
        return 10 * self.max_frame / self.baud + 0.005

    @property
    def slot_length_ms(self) -> float:
        """``slot_ms``, or by default a slot that carries :data:`SLOT_FRAMES` full frames."""
        if self.slot_ms is not None:
            return self.slot_ms
        return SLOT_FRAMES * self.max_frame * 8000 / self.link_rate_bps + self.guard_ms

    def link_ids(self, robot: str) -> tuple[int, list[int]]:
        """This robot's link id and its peers' (ConfigError when the tables do not give them).

        The one place these are worked out: the transport at start, and ``mapd check-config``
        (:meth:`check_for_robot`), so a table the start would refuse is refused by the check too.
        """
        node = self.node_id if self.node_id is not None else self.nodes.get(robot)
        if node is None:
            raise ConfigError(
                f"transports.uwb: no link id for robot '{robot}': set node_id or add it to nodes"
            )
        if self.peers:
            peer_ids = [resolve_peer(p, self.nodes) for p in self.peers]
        else:
            peer_ids = sorted(i for i in self.nodes.values() if i != node)
        if node in peer_ids:
            raise ConfigError(f"transports.uwb.peers: this robot's own link id {node} is listed as a peer")
        return node, peer_ids

    def check_files(self) -> None:
        """ValueError when ``port`` names something that is there and no serial device (a regular
        file, a folder): the start stopped on it. An absolute port not there yet is waited for at
        start (a radio the kernel names late at boot). A relative one is looked up from the working
        directory, where pyserial opens it (``/`` under systemd): it names nothing the kernel makes
        at boot (device nodes are in ``/dev``), so missing it is a mistake (``ttyUSB0`` for
        ``/dev/ttyUSB0``) that the start waited for in vain. Only ``stat`` is used: a pty or a link
        to a device is a character device too, and the port (a running daemon's) is never opened."""
        port = Path(self.port)
        if not port.is_absolute():
            found, where = from_workdir(self.port)
            said = f"'{self.port}' is relative, so mapd run opens it from {where}"
            if found is None:
                raise ValueError(f"port: {said}")
            try:
                mode = os.stat(found).st_mode
            except FileNotFoundError:
                raise ValueError(
                    f"port: {said}: {found} does not exist (name the device by its full path, such as /dev/ttyUSB0)"
                ) from None
            except OSError as exc:
                raise ValueError(f"port: {said}: {found}: {exc.strerror or exc}") from None
            if not stat.S_ISCHR(mode):
                raise ValueError(
                    f"port: {said}: {found} is not a serial device (it exists, and is no character device)"
                )
            return
        try:
            mode = os.stat(port).st_mode
        except OSError:  # not there (yet), or not ours to look at: the start says
            return
        if not stat.S_ISCHR(mode):
            raise ValueError(f"port: {port} is not a serial device (it exists, and is no character device)")

    def check_for_robot(self, robot: str) -> None:
        """ValueError for what the transport would refuse at start on robot ``robot``."""
        try:
            self.link_ids(robot)
        except ConfigError as exc:
            # named by the key at fault, as check-config names every option: "transports.uwb.peers: ..."
            text = str(exc)
            if text.startswith("transports.uwb.peers: "):
                raise ValueError(text.removeprefix("transports.uwb.")) from None
            raise ValueError("nodes: " + text.removeprefix("transports.uwb: ")) from None


def resolve_peer(spec: str, nodes: dict[str, int]) -> int:
    """A peer given as a robot name in ``nodes``, a number, or ``uwb-N``; ConfigError otherwise."""
    if spec in nodes:
        return nodes[spec]
    text = spec.removeprefix("uwb-")
    if text.isdigit() and 1 <= int(text) <= 254:
        return int(text)
    raise ConfigError(f"transports.uwb.peers: '{spec}' is not in transports.uwb.nodes nor a link id 1..254")
