"""Key expressions of the zenoh transport: how mapd names things on a zenoh bus.

Every name but one lives under ``mapd/<fleet>/``, so fleets sharing one zenoh network never see
each other's traffic (and a router ACL can fence a fleet with one rule)::

    mapd/<fleet>/<robot>/update          map updates of <robot> (packed envelopes), pub/sub
    mapd/<fleet>/<robot>                 liveliness token: <robot> is present
    mapd/<fleet>/<robot>/latest          queryable: <robot>'s latest keyframe envelope
    mapd/<fleet>/<robot>/global          <robot>'s global map (the zenoh output), put + queryable
    mapd/<fleet>/<peer>/ack/<robot>      <peer> has applied <robot>'s map version (8-byte payload)
    mapd/<fleet>/<robot>/pose            <robot>'s pose (a signed pose message), put, latest wins
    mapd/<fleet>/<robot>/takes/<bytes>   liveliness token: <robot> takes messages up to <bytes>
                                         (its limits.max_message_bytes; unsigned: limits.py)

The one outside: ``mapd/@fleets/<fleet>/<robot>``, a liveliness token that says which fleet
``<robot>`` is configured in, so robots whose ``robot.fleet`` differ, which see none of each other's
maps, can at least tell that they share a network (:mod:`transports.zenoh.fleets`). ``@fleets`` is
a zenoh verbatim chunk: no wildcard matches it (``mapd/**`` does not), and no fleet id can be it.
Only tokens live there, never data.

The ``takes`` token has five chunks and the word ``takes`` where an ack has ``ack``, so no other
subscription here matches it (presence is ``mapd/<fleet>/*``, one chunk; acks ``*/ack/<robot>``):
robots from before it see nothing new, and a robot that announces none is taken as before.

Fleet and robot ids are the config's names (``[A-Za-z0-9_-]{1,32}``), so they hold no zenoh
wildcard or separator and a key built from them matches exactly one thing. The parsers take keys
from the network: they return ``None`` for anything that is not exactly one of these shapes.
"""

from __future__ import annotations

import re

from mapd.config import NAME_PATTERN

PREFIX = "mapd"
_NAME = re.compile(NAME_PATTERN)


def valid_name(name: str) -> bool:
    """True when ``name`` can be a fleet or robot id (and so a single key-expression chunk)."""
    return _NAME.fullmatch(name) is not None


def _check(*names: str) -> None:
    for name in names:
        if not valid_name(name):
            raise ValueError(f"'{name}' is not a valid fleet or robot id ([A-Za-z0-9_-], 1 to 32 characters)")


def update_key(fleet: str, robot: str) -> str:
    """Where ``robot`` publishes its map updates."""
    _check(fleet, robot)
    return f"{PREFIX}/{fleet}/{robot}/update"


def presence_key(fleet: str, robot: str) -> str:
    """The liveliness token that says ``robot`` is present."""
    _check(fleet, robot)
    return f"{PREFIX}/{fleet}/{robot}"


def latest_key(fleet: str, robot: str) -> str:
    """The queryable that answers with ``robot``'s latest keyframe."""
    _check(fleet, robot)
    return f"{PREFIX}/{fleet}/{robot}/latest"


def global_key(fleet: str, robot: str) -> str:
    """Where ``robot``'s global map goes (the ``zenoh`` output) and is queried by late joiners."""
    _check(fleet, robot)
    return f"{PREFIX}/{fleet}/{robot}/global"


def pose_key(fleet: str, robot: str) -> str:
    """Where ``robot`` puts its pose messages."""
    _check(fleet, robot)
    return f"{PREFIX}/{fleet}/{robot}/pose"


def all_poses(fleet: str) -> str:
    """Subscription to every robot's poses in ``fleet``."""
    _check(fleet)
    return f"{PREFIX}/{fleet}/*/pose"


def ack_key(fleet: str, peer: str, robot: str) -> str:
    """Where ``peer`` says which of ``robot``'s versions it has applied."""
    _check(fleet, peer, robot)
    return f"{PREFIX}/{fleet}/{peer}/ack/{robot}"


def all_updates(fleet: str) -> str:
    """Subscription to every robot's updates in ``fleet``."""
    _check(fleet)
    return f"{PREFIX}/{fleet}/*/update"


def all_presence(fleet: str) -> str:
    """Liveliness subscription to every robot of ``fleet``."""
    _check(fleet)
    return f"{PREFIX}/{fleet}/*"


def acks_for(fleet: str, robot: str) -> str:
    """Subscription to every peer's acks of ``robot``'s versions."""
    _check(fleet, robot)
    return f"{PREFIX}/{fleet}/*/ack/{robot}"


#: The verbatim chunk under which every fleet's robots say which fleet they are of.
FLEETS = "@fleets"


def fleet_presence_key(fleet: str, robot: str) -> str:
    """The liveliness token that says ``robot`` is present and of ``fleet`` (seen by every fleet)."""
    _check(fleet, robot)
    return f"{PREFIX}/{FLEETS}/{fleet}/{robot}"


def all_fleet_presence() -> str:
    """Liveliness subscription to the fleet tokens of every robot of every fleet."""
    return f"{PREFIX}/{FLEETS}/*/*"


def parse_fleet_presence(key: str) -> tuple[str, str] | None:
    """``(fleet, robot)`` of a fleet token key, or None when ``key`` is not exactly one."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[1] != FLEETS:
        return None
    if not valid_name(parts[2]) or not valid_name(parts[3]):
        return None
    return parts[2], parts[3]


#: The least ``limits.max_message_bytes`` the config allows, and the most a ``takes`` token may say
#: (1 TiB: no map comes near; a link whose limit is larger announces this).
MIN_TAKES = 1024
MAX_TAKES = 1 << 40
# A decimal integer as ``str(int)`` writes it: ASCII digits, no sign, no leading zero, at most 13
# digits (MAX_TAKES has 13), so a key from the network never makes int() parse a huge string.
_TAKES = re.compile(r"[1-9][0-9]{3,12}")


def takes_key(fleet: str, robot: str, nbytes: int) -> str:
    """The liveliness token that says ``robot`` takes messages up to ``nbytes`` (``ValueError``
    outside :data:`MIN_TAKES` .. :data:`MAX_TAKES`)."""
    _check(fleet, robot)
    if not MIN_TAKES <= nbytes <= MAX_TAKES:
        raise ValueError(f"{nbytes} is not a message limit to announce ({MIN_TAKES} to {MAX_TAKES})")
    return f"{PREFIX}/{fleet}/{robot}/takes/{nbytes}"


def all_takes(fleet: str) -> str:
    """Liveliness subscription to what every robot of ``fleet`` takes."""
    _check(fleet)
    return f"{PREFIX}/{fleet}/*/takes/*"


def _chunks(fleet: str, key: str, n: int) -> list[str] | None:
    parts = key.split("/")
    if len(parts) != n or parts[0] != PREFIX or parts[1] != fleet:
        return None
    return parts


def parse_update(fleet: str, key: str) -> str | None:
    """The robot of an update key in ``fleet``, or None when ``key`` is not one."""
    parts = _chunks(fleet, key, 4)
    if parts is None or parts[3] != "update" or not valid_name(parts[2]):
        return None
    return parts[2]


def parse_pose(fleet: str, key: str) -> str | None:
    """The robot of a pose key in ``fleet``, or None when ``key`` is not one."""
    parts = _chunks(fleet, key, 4)
    if parts is None or parts[3] != "pose" or not valid_name(parts[2]):
        return None
    return parts[2]


def parse_presence(fleet: str, key: str) -> str | None:
    """The robot of a liveliness token key in ``fleet``, or None."""
    parts = _chunks(fleet, key, 3)
    if parts is None or not valid_name(parts[2]):
        return None
    return parts[2]


def parse_ack(fleet: str, robot: str, key: str) -> str | None:
    """The peer that sent an ack of ``robot``'s versions, or None when ``key`` is not one."""
    parts = _chunks(fleet, key, 5)
    if parts is None or parts[3] != "ack" or parts[4] != robot or not valid_name(parts[2]):
        return None
    return parts[2]


def parse_takes(fleet: str, key: str) -> tuple[str, int] | None:
    """``(robot, bytes)`` of a ``takes`` token key in ``fleet``, or None when ``key`` is not exactly
    one, or its bytes are no decimal integer within :data:`MIN_TAKES` .. :data:`MAX_TAKES`."""
    parts = _chunks(fleet, key, 5)
    if parts is None or parts[3] != "takes" or not valid_name(parts[2]):
        return None
    if _TAKES.fullmatch(parts[4]) is None:
        return None
    nbytes = int(parts[4])
    if not MIN_TAKES <= nbytes <= MAX_TAKES:
        return None
    return parts[2], nbytes
