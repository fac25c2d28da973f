"""Helpers for the zenoh transport tests: free ports, envelopes, and a robot harness.

Every session listens or connects on ``tcp/127.0.0.1:<free port>`` with multicast scouting off,
so tests never reach past loopback or see each other.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.demo.ports import free_port
from mapd.envelope import Envelope
from mapd.grid import Pose2D
from mapd.identity import Identity, Roster
from transports.base import PeerUp, Received, TransportContext, TransportEvent
from transports.zenoh import keys
from transports.zenoh.link import ZenohTransport

FLEET = "testfleet"


_IDS: dict[str, Identity] = {}
#: The test fleet's robots: each has its own key, and every signed Bot trusts all of them.
FLEET_ROBOTS = ("a", "b", "c", "m", "r1", "r2", "robot0", "robot1")


def ident(robot: str) -> Identity:
    """``robot``'s own key in the test fleet (made once per test process)."""
    if robot not in _IDS:
        _IDS[robot] = Identity.generate(robot)
    return _IDS[robot]


def roster() -> Roster:
    """The test fleet's roster (signatures required)."""
    return Roster({r: ident(r).public_key for r in FLEET_ROBOTS})


def envelope(
    robot: str, version: int, base: int = 0, payload: bytes = b"cells", signer: Identity | None = None
) -> Envelope:
    env = Envelope(
        fleet=FLEET,
        robot=robot,
        version=version,
        base_version=base,
        codec="raw",
        width=4,
        height=3,
        resolution=0.05,
        origin=Pose2D(0.0, 0.0, 0.0),
        payload=payload,
        seq=version,
    )
    return env.signed(signer) if signer is not None else env


class Bot:
    """One robot's zenoh transport in this process, recording what it emits."""

    def __init__(
        self,
        robot: str,
        *,
        listen: list[str] | None = None,
        connect: list[str] | None = None,
        signed: bool = False,
        identity: Identity | None = None,
        max_message_bytes: int = 4 << 20,
        **options: Any,
    ) -> None:
        self.events: list[TransportEvent] = []
        self.keyframe: Envelope | None = None
        self.listen = listen or []
        opts = ZenohTransport.Options(
            multicast_scouting=False, listen=self.listen, connect=connect or [], **options
        )
        self.ctx = TransportContext(
            robot=robot,
            fleet=FLEET,
            identity=identity or (ident(robot) if signed else None),
            roster=roster() if signed or identity is not None else Roster.open(),
            max_message_bytes=max_message_bytes,
            emit=self.events.append,
            latest_keyframe=lambda: self.keyframe,
        )
        self.t = ZenohTransport(opts, self.ctx)

    async def start(self) -> Bot:
        await self.t.start()
        return self

    def offer(self, env: Envelope) -> None:
        if env.is_keyframe:
            self.keyframe = env  # what the daemon would keep for late joiners
        self.t.offer(env)

    def of(self, kind: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    def received(self, peer: str | None = None) -> list[tuple[str, int, int]]:
        """(peer, version, base) of every Received, unpacked for reading."""
        from mapd.envelope import unpack

        out = []
        for e in self.of(Received):
            env = unpack(e.data)
            if peer is None or e.peer == peer:
                out.append((e.peer, env.version, env.base_version))
        return out

    async def wait(self, cond: Callable[[], bool], timeout: float = 5.0) -> None:
        """Wait until ``cond()`` holds; fail the test (showing the events) after ``timeout``."""
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(
                    f"{self.ctx.robot}: condition not met in {timeout} s; events: {self.events}; {self.t.stats()}"
                )
            await asyncio.sleep(0.01)


async def meet(*bots: Bot, timeout: float = 5.0) -> None:
    """Wait until every bot sees every other one's token. A token is declared after the
    subscribers, so a robot that sees a peer's token also knows where to send it updates."""
    for bot in bots:
        others = sorted(o.ctx.robot for o in bots if o is not bot)
        # PeerUp, not peers(): in a signed fleet peers() also waits for a verified message
        await bot.wait(
            lambda bot=bot, others=others: all(PeerUp("zenoh", r) in bot.events for r in others), timeout
        )


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Fleet:
    """The bots one test starts; :func:`fleet` closes them all at the end (closing twice is harmless)."""

    def __init__(self) -> None:
        self.bots: list[Bot] = []
        #: Where the first robot listens and the others connect, unless a test wires its own.
        self.ep = endpoint(free_port())

    async def start(self, robot: str, **kw: Any) -> Bot:
        bot = await Bot(robot, **kw).start()
        self.bots.append(bot)
        return bot

    async def close(self) -> None:
        for bot in reversed(self.bots):
            await bot.t.close()


@asynccontextmanager
async def fleet() -> AsyncIterator[Fleet]:
    """A :class:`Fleet` whose bots are closed however the test ends."""
    f = Fleet()
    try:
        yield f
    finally:
        await f.close()


@asynccontextmanager
async def pair(
    listener: str = "a", connector: str = "b", *, meet_first: bool = True, **kw: Any
) -> AsyncIterator[tuple[Bot, Bot]]:
    """Two robots: ``listener`` listens, ``connector`` connects to it; yielded in that order, after
    they have met (each sees the other's token) unless ``meet_first`` is false. ``kw`` goes to both."""
    async with fleet() as f:
        one = await f.start(listener, listen=[f.ep], **kw)
        two = await f.start(connector, connect=[f.ep], **kw)
        if meet_first:
            await meet(one, two)
        yield one, two


class RawSession:
    """A plain zenoh session (no mapd) connected to ``ep``, to put what no robot would.

    ``seen`` fills once it has ``watch``'s liveliness token: zenoh's gossip has then connected it to
    that robot too, so what it puts reaches it.
    """

    def __init__(self, ep: str, watch: str) -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", f'["{ep}"]')
        self.session = zenoh.open(conf)
        self.seen: list[str] = []
        self._token_sub = self.session.liveliness().declare_subscriber(
            keys.presence_key(FLEET, watch), lambda s: self.seen.append(str(s.key_expr)), history=True
        )

    def put(self, key: str, data: bytes) -> None:
        import zenoh

        # Blocking, not zenoh's default (drop): on a loaded machine a 100 kB put was dropped by
        # the raw session's own congestion control, and a test waited for what never left.
        self.session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)

    def close(self) -> None:
        self._token_sub.undeclare()
        self.session.close()


@contextmanager
def raw_session(ep: str, watch: str) -> Iterator[RawSession]:
    """A :class:`RawSession`, closed at the end."""
    raw = RawSession(ep, watch)
    try:
        yield raw
    finally:
        raw.close()


@pytest.fixture
def zk() -> SimpleNamespace:
    """The helpers above, for test modules (importlib mode keeps conftest out of reach of imports)."""
    return SimpleNamespace(
        Bot=Bot,
        meet=meet,
        envelope=envelope,
        ident=ident,
        roster=roster,
        free_port=free_port,
        endpoint=endpoint,
        fleet=fleet,
        pair=pair,
        raw_session=raw_session,
        FLEET=FLEET,
    )
