"""One exception family for everything mapd reports to a user.

Every error that comes from untrusted input (files, configs, serial bytes, network payloads) or
from the environment (a missing serial port, a read-only state directory) is a :class:`MapdError`.
The CLI turns one into a single line on stderr and a non-zero exit; any other exception is a bug.

The exit status is :func:`exit_code`'s, one convention for every command and for ``mapd run``'s
start, which the unit (``deploy/mapd.service``) relies on:

* **1**: a failure a later try may get past: a radio or router not there, another mapd holding the
  state directory, a full disk, a link that stopped. systemd starts the unit again
  (``Restart=on-failure``).
* **2**: the config, or a path or file it names, that this robot cannot use as it is: a typo, a
  missing key file, a state directory, output folder or control socket the unit's user may not
  create, a read-only file system, a file where a folder goes. No retry heals one, so the unit is
  not restarted (``RestartPreventExitStatus=2``): fix it, then ``systemctl restart mapd``. (A usage
  error that argparse refuses exits 2 as well.)

Commands choose others of their own (``3``: ``mapd bench`` stopped after an epoch; ``130``: an
interrupt).
"""

from __future__ import annotations

import errno


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


#: errno values that say a path cannot be used as the config names it, for as long as nobody changes
#: the machine or the config: who may write there, a read-only file system, a file where a folder
#: goes (or the other way round), a name too long, a loop of links. ENOENT is not among them: a
#: folder on a mount not there yet (an SD card) may be there at the next try.
UNUSABLE_PATH_ERRNOS = frozenset(
    {
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.ENOTDIR,
        errno.EISDIR,
        errno.EEXIST,
        errno.ENAMETOOLONG,
        errno.ELOOP,
    }
)
#: errno values of a full disk: it may have room at the next try (:class:`DiskFullError`).
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


def os_cause(exc: BaseException) -> OSError | None:
    """The OSError that ``exc`` was raised from, or while handling, or None.

    mapd raises its errors ``from None`` inside ``except OSError`` so that the user sees one line and
    no traceback; Python keeps the OSError as ``__context__`` all the same. Followed through other
    MapdErrors only (a StateError made of the MapdError of a failed write), never past an unrelated
    exception.
    """
    link = exc.__cause__ or exc.__context__
    for _ in range(8):  # (a chain is 1 or 2 long; a bound, not a walk of whatever was linked)
        if isinstance(link, OSError):
            return link
        if not isinstance(link, MapdError):
            return None
        link = link.__cause__ or link.__context__
    return None


def exit_code(exc: MapdError) -> int:
    """The exit status for ``exc``, by the convention in this module's docstring.

    Decided by what went wrong, not by which part noticed: an output folder and the state directory
    that the unit's user may not create are the same mistake, so both exit 2 (the first was a
    ConfigError, the second a StateError that exited 1, and systemd restarted it every 2 s for
    ever). A full disk exits 1 whoever meets it.
    """
    cause = os_cause(exc)
    if isinstance(exc, DiskFullError) or (cause is not None and cause.errno in DISK_FULL_ERRNOS):
        return MapdError.exit_code
    if isinstance(exc, ConfigError):
        return ConfigError.exit_code
    # The state directory, a recording's folder, the control socket: paths the config names.
    if (
        isinstance(exc, StateError | DaemonError)
        and cause is not None
        and cause.errno in UNUSABLE_PATH_ERRNOS
    ):
        return ConfigError.exit_code
    return exc.exit_code
