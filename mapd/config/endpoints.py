"""Addresses a config names, checked as the start will use them, without opening anything.

A zenoh endpoint (``listen``, ``connect`` of the zenoh transport and output and of the ros2 source
and output) was checked for its shape alone: ``tcp/notanaddress``, a port past 65535 or a protocol
zenoh does not have passed ``mapd check-config`` and stopped ``mapd run`` when the session opened;
so did two parts of one config (the view, the zenoh transport, a zenoh output) listening on one
port. (TLS files a zenoh config names: :mod:`mapd.ros2.zenoh_config`, with the config files.) Host names are not
resolved here: DNS, like the machine's interfaces and who else holds a port, is the start's to meet.
"""

from __future__ import annotations

import ipaddress
import re
from typing import NamedTuple

from pydantic import field_validator

# <protocol>/<address>[?<metadata>][#<config>], e.g. tcp/127.0.0.1:7447, tls/host:7447, udp/[::1]:7447
_ENDPOINT = re.compile(r"[a-z][a-z0-9+\-]*/[^\s]+")
#: Every link protocol zenoh has (a build may lack some: unixpipe, serial and vsock are not in the
#: eclipse-zenoh wheel, and its session says so at start).
PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
#: The protocols whose address is HOST:PORT, and the socket kind each listens with.
_ON_IP = {"tcp": "tcp", "tls": "tcp", "ws": "tcp", "udp": "udp", "quic": "udp"}
#: Where a zenoh router listens when nothing says otherwise.
ROUTER_DEFAULT = "tcp/[::]:7447"
# (an underscore too: /etc/hosts and some DNS zones hold such names, and getaddrinfo takes them)
_LABEL = re.compile(r"(?!-)[A-Za-z0-9_-]{1,63}(?<!-)")


def host_problem(host: str) -> str | None:
    """Why no socket can be bound or connected at ``host`` (brackets stripped), or None: it is an
    IP address or a well-formed host name (which the start resolves)."""
    try:
        ipaddress.ip_address(host)
        return None
    except ValueError:
        pass
    if re.fullmatch(r"[0-9.]+", host):
        return f"'{host}' is not an IP address"
    name = host.removesuffix(".")
    if len(name) > 253 or not all(_LABEL.fullmatch(label) for label in name.split(".")):
        return f"'{host}' is neither an IP address nor a host name"
    return None


def split_host_port(address: str, *, lowest_port: int = 0) -> tuple[str, int]:
    """``"HOST:PORT"`` (``"[::1]:8080"`` for IPv6) -> ``(host, port)``, brackets stripped; ValueError
    (a phrase, for the caller to name the option) when malformed.

    The one reading of HOST:PORT for the view's ``listen`` and zenoh's endpoints on IP, so both take
    and refuse the same addresses: an IPv6 address without brackets is refused rather than split at
    its last colon. The view needs a port a browser can be told (``lowest_port=1``); a zenoh listener
    may take port 0 (any free port).
    """
    host, sep, port = address.rpartition(":")
    bracketed = host.startswith("[") and host.endswith("]")
    if (
        not sep
        or not host
        or not (port.isascii() and port.isdigit())
        or not lowest_port <= int(port) <= 65535
    ):
        raise ValueError(f"needs HOST:PORT with a port {lowest_port}-65535")
    if ":" in host and not bracketed:
        raise ValueError(f"needs an IPv6 address in brackets, as in [::1]:{port}")
    if host.startswith("[") != host.endswith("]"):
        raise ValueError(f"needs HOST:PORT, and '{host}' has an unpaired bracket")
    return host[1:-1] if bracketed else host, int(port)


def _split(ep: str) -> tuple[str, str, int] | None:
    """``(protocol, host, port)`` of an endpoint on IP, or None for one of another kind."""
    proto, _, rest = ep.partition("/")
    if proto not in _ON_IP:
        return None
    try:
        host, port = split_host_port(re.split(r"[?#]", rest, maxsplit=1)[0])
    except ValueError as exc:
        raise ValueError(f"'{ep}': {proto} {exc}") from None
    return proto, host, port


def check_endpoints(endpoints: list[str]) -> list[str]:
    """``endpoints`` if zenoh can use each; ValueError with one line for the first it cannot."""
    for ep in endpoints:
        if not _ENDPOINT.fullmatch(ep):
            raise ValueError(
                f"'{ep}' is not a zenoh endpoint (<protocol>/<address>, e.g. tcp/127.0.0.1:7447)"
            )
        proto = ep.partition("/")[0]
        if proto not in PROTOCOLS:
            raise ValueError(f"'{ep}': zenoh has no link protocol '{proto}' (it has {', '.join(PROTOCOLS)})")
        split = _split(ep)
        if split is not None and (problem := host_problem(split[1].partition("%")[0])):
            raise ValueError(f"'{ep}': {problem}")
    return endpoints


class ZenohEndpoints:
    """For plugin options whose ``listen`` and ``connect`` are zenoh endpoints (the zenoh transport
    and output, the ros2 source and output): each is checked as the session will use it."""

    @field_validator("listen", "connect", check_fields=False)
    @classmethod
    def _check_endpoints(cls, v: list[str]) -> list[str]:
        return check_endpoints(v)


def listening(options: object) -> list[tuple[str, str]]:
    """The zenoh endpoints a plugin's options listen on, each with how to name it: its ``listen``,
    else a router's default (unless a zenoh config file it names may set another)."""
    listen = getattr(options, "listen", None)
    if isinstance(listen, list) and listen:
        return [(ep, ep) for ep in listen if isinstance(ep, str)]
    files = [getattr(options, name, None) for name in getattr(options, "beside_config", ())]
    if getattr(options, "mode", None) == "router" and not any(files):
        return [(ROUTER_DEFAULT, f"{ROUTER_DEFAULT} (a router's default)")]
    return []


def socket_of(ep: str) -> Listener | None:
    """What listening on zenoh endpoint ``ep`` binds, or None (not on IP, or port 0: any free port).

    zenoh's IPv6 wildcard (``[::]``, a router's default) takes IPv4 too, as Linux binds it unless
    ``net.ipv6.bindv6only`` is set: a view on 127.0.0.1 found its port taken by a router's 7447.
    """
    try:
        split = _split(ep)
    except ValueError:
        return None
    if split is None or split[2] == 0:
        return None
    return Listener(_ON_IP[split[0]], split[1], split[2], both_families=True)


class Listener(NamedTuple):
    """A listening socket: ``tcp`` or ``udp``, the host as written, the port, and whether an IPv6
    wildcard there takes IPv4 as well (zenoh's does; asyncio's, the view's, is IPv6 only)."""

    kind: str
    host: str
    port: int
    both_families: bool = False


def same_socket(a: Listener, b: Listener) -> bool:
    """Whether two listeners would take one socket: the same kind and port, and the same address
    or one the other's wildcard (host names are compared as written, never resolved)."""
    if a.kind != b.kind or a.port != b.port:
        return False
    try:
        ha, hb = ipaddress.ip_address(a.host), ipaddress.ip_address(b.host)
    except ValueError:
        return a.host == b.host
    if ha == hb or (ha.version == hb.version and (ha.is_unspecified or hb.is_unspecified)):
        return True
    # an IPv6 wildcard that takes both families, beside an IPv4 address
    return any(x.version == 6 and x.is_unspecified and lx.both_families for x, lx in ((ha, a), (hb, b)))
