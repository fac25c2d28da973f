"""rmw_zenoh's wire conventions as pure functions: keys, liveliness tokens, QoS strings, GIDs, attachments.

Everything here is sans-I/O (strings and bytes in, strings and bytes out; no session, no clock), so
each rule can be checked on its own. The formats are rmw_zenoh_cpp's (``ros2/rmw_zenoh``,
``docs/design.md`` and ``rmw_zenoh_cpp/src/detail/``):

* **Data key** (``TopicInfo``, ``liveliness_utils.cpp``):
  ``<domain_id>/<fully qualified topic, leading and trailing '/' stripped>/<dds type>/<type hash>``,
  e.g. ``0/robot1/map/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_8d34...``. The dds type is the
  ROS type with ``dds_`` before the name and a trailing underscore. The type hash is the RIHS01 hash
  of the type description (Jazzy and later) or ``TypeHashNotSupported`` (Humble, which has no type
  hashes).
* **Liveliness token** (``Entity::Entity``): ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/
  <namespace>/<node name>`` and, for publishers (``MP``) and subscriptions (``MS``),
  ``/<topic>/<dds type>/<type hash>/<qos>``. Every name is *mangled*: each ``/`` becomes ``%``
  (``mangle_name``), so the root namespace ``/`` and the default enclave ``/`` are ``%`` and the
  topic ``/map`` is ``%map``. ``<zid>`` is the session's zenoh id as zenoh prints it; ``<nid>`` is
  the node's entity id and ``<eid>`` the entity's, both from one counter per context (a node's
  ``eid`` is its ``nid``).
* **QoS string** (``qos_to_keyexpr``): ``<reliability>:<durability>:<history>,<depth>:<deadline s>,
  <deadline ns>:<lifespan s>,<lifespan ns>:<liveliness>,<lease s>,<lease ns>`` with the ``rmw/types.h``
  enum values, and every field equal to rmw_zenoh's default (``qos.cpp``: reliable, volatile, keep
  last, depth 42, infinite durations, automatic liveliness) left empty. A reliable, transient-local,
  keep-last-1 publisher (a ``/map``) is ``:1:,1:,:,:,,``.
* **GID**: the XXH3-128 hash of the entity's whole liveliness token, its low 64 bits then its high 64
  bits, each little-endian (``simplified_XXH3_128bits`` in ``Entity::Entity``).
* **Attachment** (``attachment_helpers.cpp``): zenoh-ext serialization of the sequence number
  (int64), the source timestamp (int64 ns since the epoch) and the GID (``std::array<uint8_t, 16>``,
  serialized as a sequence: a LEB128 length, 16, then the bytes): 33 bytes, little-endian.

``zenoh-bridge-ros2dds`` keys (the ``ros2dds`` format) are the topic without its leading slash under
an optional namespace, with plain CDR payloads and no attachment.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Literal

from mapd.errors import CodecError
from mapd.grid.reprs import short_repr

Distro = Literal["humble", "jazzy", "kilted", "rolling"]
DISTROS: tuple[str, ...] = ("humble", "jazzy", "kilted", "rolling")
KeyFormat = Literal["rmw_zenoh", "ros2dds"]
EntityKind = Literal["NN", "MP", "MS", "SS", "SC"]

ADMIN_SPACE = "@ros2_lv"
#: What rmw_zenoh on Humble puts where later distros put the RIHS01 type hash.
NO_TYPE_HASH = "TypeHashNotSupported"
ATTACHMENT_BYTES = 8 + 8 + 1 + 16

# rmw/types.h enum values.
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


@dataclass(frozen=True)
class Qos:
    """The QoS an rmw_zenoh entity announces (durations infinite and liveliness automatic, its defaults)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42


#: rmw_zenoh's default QoS (``qos.cpp``): fields equal to it are left empty in tokens.
DEFAULT_QOS = Qos()
#: ``/map``, ``/tf_static``: reliable, transient local, keep last 1 (what map_server and RViz use).
LATCHED = Qos(RELIABLE, TRANSIENT_LOCAL, KEEP_LAST, 1)
#: ``/tf``: reliable, volatile, keep last 100 (tf2_ros's TransformBroadcaster).
TF_QOS = Qos(RELIABLE, VOLATILE, KEEP_LAST, 100)
#: ``/diagnostics``: reliable, volatile, keep last 1 (diagnostic_updater's publisher).
DIAGNOSTICS_QOS = Qos(RELIABLE, VOLATILE, KEEP_LAST, 1)


def qos_string(qos: Qos) -> str:
    """rmw_zenoh's ``qos_to_keyexpr``: default fields empty, durations and liveliness at their defaults."""
    d = DEFAULT_QOS

    def part(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (
        f"{part(qos.reliability, d.reliability)}:{part(qos.durability, d.durability)}:"
        f"{part(qos.history, d.history)},{part(qos.depth, d.depth)}:,:,:,,"
    )


def parse_qos(text: str) -> Qos:
    """The inverse of :func:`qos_string` (``keyexpr_to_qos``); ValueError for a malformed string."""
    parts = text.split(":")
    if len(parts) < 6:
        raise ValueError(f"not an rmw_zenoh QoS string: {text!r}")
    hist = parts[2].split(",")
    if len(hist) < 2:
        raise ValueError(f"not an rmw_zenoh QoS string: {text!r}")
    d = DEFAULT_QOS

    def num(s: str, default: int) -> int:
        return default if s == "" else int(s)

    return Qos(
        num(parts[0], d.reliability),
        num(parts[1], d.durability),
        num(hist[0], d.history),
        num(hist[1], d.depth),
    )


def mangle(name: str) -> str:
    """rmw_zenoh's ``mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def dds_type(msgtype: str) -> str:
    """``nav_msgs/msg/OccupancyGrid`` -> ``nav_msgs::msg::dds_::OccupancyGrid_`` (rmw_zenoh's type name)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@lru_cache(maxsize=16)
def type_hash(msgtype: str, distro: Distro) -> str:
    """The type hash rmw_zenoh puts in keys and tokens for ``msgtype`` on ``distro``."""
    if distro == "humble":
        return NO_TYPE_HASH
    return str(typestore(distro).hash_rihs01(msgtype))


_STORES = {"humble": "ROS2_HUMBLE", "jazzy": "ROS2_JAZZY", "kilted": "ROS2_KILTED", "rolling": "LATEST"}


@lru_cache(maxsize=4)
def typestore(distro: str = "jazzy") -> Any:
    """rosbags' type store of a ROS 2 distro (``rolling``: rosbags' latest), for CDR and type hashes."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError:
        raise CodecError("ROS 2 messages need rosbags (pip install 'mapd[ros2]')") from None
    return get_typestore(getattr(Stores, _STORES.get(distro, "ROS2_JAZZY")))


def check_name(name: str, what: str = "topic") -> str:
    """A ROS 2 name without leading/trailing ``/``; ValueError for an empty part or a zenoh wildcard."""
    inner = name.strip("/")
    if not inner or any(not p for p in inner.split("/")) or any(c in inner for c in "*$?#%@ "):
        raise ValueError(f"not a ROS 2 {what} name: {name!r}")
    return inner


#: One token of an rcl name (``rcl_validate_topic_name``): ASCII letters, digits and ``_``, not
#: starting with a digit.
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: What no frame id of mapd's may hold: zenoh's wildcards and separators (refused since the first
#: release; a frame never needs them).
_NOT_IN_FRAMES = "*$?#%@"


def check_topic_name(name: str, what: str = "topic") -> str:
    """``name`` when it is a topic (or namespace) name rcl accepts, else ValueError with one line.

    rcl's grammar: tokens of ``[A-Za-z_][A-Za-z0-9_]*`` separated by single ``/``, an optional
    leading ``/`` (absolute; relative names are taken under the node's namespace), no trailing
    ``/``. A name no ROS node can spell (``my-map``, ``/map/``, ``2d/map``) would be published
    where nothing ever subscribes. ``~`` (the node's private namespace) and ``{}`` substitutions are
    rcl's too, but mapd does not expand them, so they are refused rather than sent as they are.
    """
    if name.startswith("~") or "{" in name:
        raise ValueError(
            f"{what} {short_repr(name)}: mapd does not expand '~' or '{{...}}' in ROS 2 names; write it in full"
        )
    body = name[1:] if name.startswith("/") else name
    if not body or not all(_TOKEN.fullmatch(t) for t in body.split("/")):
        raise ValueError(
            f"not a ROS 2 {what} name: {short_repr(name)} (rcl: tokens of A-Z a-z 0-9 _, none starting "
            "with a digit, separated by single '/', no '/' at the end)"
        )
    return name


def check_namespace(namespace: str) -> str:
    """``namespace`` when it is a namespace rcl accepts (``/fleet``, ``fleet`` and ``fleet/`` are one
    namespace; empty or ``/``: the root), else ValueError with one line."""
    ns = namespace.strip("/")
    if ns:
        check_topic_name(ns, "namespace")
    return namespace


def check_frame_id(frame: str, *, shown: str | None = None) -> str:
    """``frame`` when tf2 takes it as written, else ValueError with one line.

    tf2 (``buffer_core.cpp``) refuses a frame id that starts with ``/`` in every lookup and strips
    it when a transform is set, so ``/map`` and ``map`` are one frame to it but not to mapd's own
    comparisons; it refuses an empty one. Nothing else is tf2's rule: robot names (``robot-1``,
    ``2nd``) make frame ids outside rcl's name grammar, which tf2 and RViz take. What is refused
    besides: whitespace, control and non-ASCII characters (invisible or ambiguous in every tool
    that shows frames), an empty part (``a//b``, ``map/``) and zenoh's wildcard characters.
    ``shown``: the name the message shows (a ``{robot}`` template rather than its expansion).
    """
    what = short_repr(frame if shown is None else shown)
    if not frame:
        raise ValueError("a tf2 frame id cannot be empty")
    if frame.startswith("/"):
        raise ValueError(
            f"{what}: a tf2 frame id has no leading '/' (tf2 refuses it in lookups); "
            f"write {short_repr((frame if shown is None else shown).lstrip('/'))}"
        )
    if (
        not (frame.isascii() and frame.isprintable())
        or " " in frame
        or any(c in frame for c in _NOT_IN_FRAMES)
    ):
        raise ValueError(
            f"{what}: a frame id here is printable ASCII without spaces or any of {_NOT_IN_FRAMES}"
        )
    if any(not part for part in frame.split("/")):
        raise ValueError(f"{what}: a frame id has no empty part ('a//b', or a '/' at the end)")
    return frame


def key_exprs_intersect(a: str, b: str) -> bool:
    """Whether zenoh key expressions ``a`` and ``b`` can match one key (``*``, ``**``, ``$*``), as
    zenoh itself decides it (``KeyExpr.intersects``)."""
    import zenoh  # only where a config is checked: rmw's other helpers stay free of it

    return bool(zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)))


def fq_topic(topic: str, namespace: str = "") -> str:
    """The fully qualified name: an absolute topic as is, a relative one under ``namespace``."""
    if topic.startswith("/"):
        return "/" + check_name(topic)
    ns = namespace.strip("/")
    return "/" + (f"{check_name(ns, 'namespace')}/" if ns else "") + check_name(topic)


def fq_namespace(namespace: str) -> str:
    """A node namespace as rcl holds it: ``/`` for the root, else ``/a/b``."""
    ns = namespace.strip("/")
    return "/" + check_name(ns, "namespace") if ns else "/"


def data_key(
    topic: str, msgtype: str, *, domain: int = 0, distro: Distro = "jazzy", hash_: str | None = None
) -> str:
    """rmw_zenoh's data key of a fully qualified ``topic`` (``hash_='*'`` for a subscription wildcard)."""
    h = type_hash(msgtype, distro) if hash_ is None else hash_
    return f"{domain}/{check_name(topic)}/{dds_type(msgtype)}/{h}"


def bridge_key(topic: str, *, namespace: str = "") -> str:
    """zenoh-bridge-ros2dds's key: the topic without its leading slash, under ``namespace`` if given."""
    ns = namespace.strip("/")
    name = check_name(topic)
    return f"{check_name(ns, 'namespace')}/{name}" if ns else name


@dataclass(frozen=True)
class Entity:
    """One rmw_zenoh graph entity: a node (``NN``), a publisher (``MP``) or a subscription (``MS``)."""

    domain: int
    zid: str
    nid: int
    eid: int
    kind: EntityKind
    namespace: str  # fully qualified ("/" or "/a/b")
    node: str
    enclave: str = "/"
    topic: str | None = None  # fully qualified
    type: str | None = None  # the dds type name
    type_hash: str | None = None
    qos: Qos | None = field(default=None)

    def token(self) -> str:
        """The liveliness key expression rmw_zenoh declares for this entity."""
        parts = [
            ADMIN_SPACE,
            str(self.domain),
            self.zid,
            str(self.nid),
            str(self.eid),
            self.kind,
            mangle(self.enclave),
            mangle(self.namespace),
            mangle(self.node),
        ]
        if self.kind != "NN":
            if self.topic is None or self.type is None or self.type_hash is None or self.qos is None:
                raise ValueError(f"a {self.kind} entity needs a topic, type, type hash and QoS")
            parts += [mangle(self.topic), mangle(self.type), mangle(self.type_hash), qos_string(self.qos)]
        return "/".join(parts)

    def gid(self) -> bytes:
        """The 16-byte GID rmw_zenoh derives from the token (XXH3-128: low, then high, little-endian)."""
        return gid_of(self.token())


def gid_of(token: str) -> bytes:
    """XXH3-128 of ``token``: its low 64 bits then its high 64 bits, each little-endian."""
    try:
        import xxhash
    except ModuleNotFoundError:
        raise CodecError("rmw_zenoh GIDs need xxhash (pip install 'mapd[ros2]')") from None
    value = xxhash.xxh3_128_intdigest(token.encode())
    return (value & (2**64 - 1)).to_bytes(8, "little") + (value >> 64).to_bytes(8, "little")


def parse_token(key: str) -> Entity:
    """An :class:`Entity` from a liveliness key expression; ValueError for anything else."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        raise ValueError(f"not an rmw_zenoh liveliness token: {key!r}")
    kind = parts[5]
    if kind not in ("NN", "MP", "MS", "SS", "SC"):
        raise ValueError(f"unknown entity kind {kind!r} in {key!r}")
    common: dict[str, Any] = {
        "domain": int(parts[1]),
        "zid": parts[2],
        "nid": int(parts[3]),
        "eid": int(parts[4]),
        "kind": kind,
        "enclave": demangle(parts[6]),
        "namespace": demangle(parts[7]),
        "node": demangle(parts[8]),
    }
    if kind == "NN":
        return Entity(**common)
    if len(parts) < 13:
        raise ValueError(f"a {kind} token without topic, type, hash and QoS: {key!r}")
    return Entity(
        **common,
        topic=demangle(parts[9]),
        type=demangle(parts[10]),
        type_hash=demangle(parts[11]),
        qos=parse_qos(parts[12]),
    )


def attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment rmw_zenoh puts on every sample (see the module docstring)."""
    if len(gid) != 16:
        raise ValueError("an rmw GID has 16 bytes")
    return struct.pack("<qq", sequence, timestamp_ns) + b"\x10" + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence, source timestamp in ns, GID) from an rmw_zenoh attachment; CodecError when malformed."""
    if len(data) != ATTACHMENT_BYTES or data[16] != 16:
        raise CodecError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    seq, stamp = struct.unpack_from("<qq", data)
    return seq, stamp, bytes(data[17:])
