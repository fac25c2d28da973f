"""One exception family for everything mapd reports to a user.

Every error that comes from untrusted input (files, configs, serial bytes, network payloads) or
from the environment (a missing serial port, a read-only state directory) is a :class:`MapdError`.
The CLI turns one into a single line on stderr and a non-zero exit; any other exception is a bug.
"""

from __future__ import annotations


class MapdError(Exception):
    """Base of every error mapd raises on purpose. ``str(err)`` is one line for the user."""

    exit_code = 1


class ConfigError(MapdError):
    """A config file or option is missing, malformed or names something that does not exist."""

    exit_code = 2


class MapFileError(MapdError):
    """A map_server YAML or image cannot be read, or breaks map_server's rules."""


class LimitError(MapdError):
    """Input asks for more than a configured limit (cells, bytes, queue length)."""


class CodecError(MapdError):
    """A payload cannot be encoded or decoded: truncated, corrupt, wrong base, unknown codec."""


class EnvelopeError(MapdError):
    """An update envelope is malformed, too large, unsigned or badly signed."""


class SignatureError(EnvelopeError):
    """A message is unsigned while a key is required, or its signature does not verify.

    Raised by envelope (and ack) verification; transports and the daemon catch it by type to count
    forgeries apart from damaged bytes.
    """


class PluginError(MapdError):
    """A plugin cannot be found or imported (for example, an optional dependency is missing)."""


class TransportError(MapdError):
    """A transport cannot start or has failed (missing serial port, zenoh session refused)."""


class UnreachableError(TransportError):
    """A session found none of the endpoints it must connect to answering (its router not up yet,
    or out of reach): worth trying again, unlike a refusal by a router that answered."""


class ProtocolError(TransportError):
    """Bytes on a link break the wire protocol (bad frame, absurd field). Counted, never fatal."""


class SourceError(MapdError):
    """A map source cannot produce maps (missing log, bad line, vanished map file)."""


class FusionError(MapdError):
    """Maps cannot be fused (incompatible inputs)."""


class StateError(MapdError):
    """The state directory cannot be read or written."""


class DiskFullError(StateError):
    """A write found no room (ENOSPC, EDQUOT): unlike a permission, it may go through once the disk
    has room again, so whoever meets it at start-up runs on and tries again."""


class DaemonError(MapdError):
    """The daemon cannot start, or no daemon answers on the control socket."""
