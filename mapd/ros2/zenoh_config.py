"""A zenoh config file read as untrusted input: one error line, never a hang or a huge read.

``zenoh.Config.from_file`` opens whatever the path names: a FIFO without a writer blocked
``mapd run`` for ever (in a thread that ignored SIGTERM), and ``/dev/zero`` was read until memory
ran out. Here the file must be a regular file of at most :data:`MAX_ZENOH_CONFIG_BYTES`, is read
by mapd, and its text handed to zenoh: JSON5 as is, YAML (``.yaml``, ``.yml``) as JSON, which is
what zenoh's own loader does with those suffixes.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from mapd.errors import TransportError, UnreachableError
from mapd.files.folders import from_workdir
from mapd.files.reading import NotRegularFileError, open_regular

#: zenoh's own example config, every option commented, is about 30 KiB.
MAX_ZENOH_CONFIG_BYTES = 1 << 20
#: The TLS files a zenoh config may name, with what each must hold, and the most read of one.
_TLS_FILES = {
    "root_ca_certificate": "CERTIFICATE-----",
    "listen_certificate": "CERTIFICATE-----",
    "connect_certificate": "CERTIFICATE-----",
    "listen_private_key": "PRIVATE KEY-----",
    "connect_private_key": "PRIVATE KEY-----",
}
_MAX_PEM = 1 << 20


def zenoh_config_text(path: Path) -> str:
    """The config in ``path`` as JSON5 text for ``zenoh.Config.from_json5``.

    Raises ValueError with one line (without the path) for a file that is not a regular file,
    cannot be read, is too large, not UTF-8, or not YAML when named so.
    """
    try:
        with open_regular(path) as fh:
            raw = fh.read(MAX_ZENOH_CONFIG_BYTES + 1)
    except NotRegularFileError:
        raise ValueError("not a regular file") from None
    except OSError as exc:
        raise ValueError(f"cannot read it: {exc.strerror or exc}") from None
    if len(raw) > MAX_ZENOH_CONFIG_BYTES:
        raise ValueError(f"over {MAX_ZENOH_CONFIG_BYTES >> 20} MiB; a zenoh config is a few KiB")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError("not UTF-8 text") from None
    if path.suffix.lower() not in (".yaml", ".yml"):
        return text
    import yaml

    try:
        doc = yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError) as exc:
        raise ValueError(f"malformed YAML ({type(exc).__name__})") from None
    try:
        return json.dumps(doc)
    except (TypeError, ValueError, RecursionError):  # dates, sets: nothing zenoh reads
        raise ValueError("YAML that holds no zenoh config") from None


def zenoh_message(exc: BaseException) -> str:
    """zenoh's error text on one line, without the Rust source location it appends."""
    text = " ".join(str(exc).split())
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    return text.rstrip(".") or type(exc).__name__


T = TypeVar("T")

#: Seconds before the first new try to open a session whose routers could not be reached; it
#: doubles after each failed try, up to :data:`RETRY_MAX_S`.
RETRY_FIRST_S = 1.0
RETRY_MAX_S = 30.0


#: Seconds to wait for a TCP answer from an endpoint a session could not connect to.
PROBE_TIMEOUT_S = 1.0
_ENDPOINT = re.compile(r"\b(?:tcp|tls|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.\-_]+):(\d{1,5})\b")


def _any_answers(message: str) -> bool:
    """Whether any TCP-based endpoint named in zenoh's message takes a TCP connection: then a router
    is there and refused us (a certificate, an ACL, a protocol), which no retry mends."""
    for host, port in _ENDPOINT.findall(message):
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=PROBE_TIMEOUT_S):
                return True
        except (OSError, ValueError):
            continue
    return False


def open_zenoh(conf: Any, what: str) -> Any:
    """``zenoh.open(conf)`` (blocking: call it off the event loop); a refusal as one line prefixed
    ``what``: :class:`UnreachableError` when no endpoint it must connect to answers at all, else
    :class:`TransportError` (a bad config, a port in use, a router that refused us)."""
    import zenoh

    try:
        return zenoh.open(conf)
    except Exception as exc:  # zenoh.ZError
        message = zenoh_message(exc)
        if "Unable to connect to any of" in message:
            if not _any_answers(message):
                raise UnreachableError(f"{what}: {message}") from None
            # said in words: zenoh's own are the same as for a router that is not there
            message += " (something answers there and refused the session: its certificate, ACL or version?)"
        raise TransportError(f"{what}: {message}") from None


async def open_when_reachable(
    open_session: Callable[[], T],
    *,
    on_refusal: Callable[[TransportError], None] | None = None,
    run: Callable[[Callable[[], T]], Awaitable[T]] = asyncio.to_thread,
) -> T:
    """Call ``open_session`` (blocking: on ``run``'s thread, a worker by default) after
    :data:`RETRY_FIRST_S`, then after twice as long each time up to :data:`RETRY_MAX_S`, until it
    opens. For a session that found no router at start, while the daemon runs on. An error other
    than :class:`UnreachableError` is raised, unless ``on_refusal`` takes it (and the tries go on:
    an output has no way to stop the daemon, and systemd would restart it into the same tries).

    Cancelling the wait does not stop a try under way in its thread: ``open_session`` must itself
    close what it opened when its owner closed meanwhile."""
    delay = RETRY_FIRST_S
    while True:
        await asyncio.sleep(delay)
        try:
            return await run(open_session)
        except Exception as exc:
            if isinstance(exc, UnreachableError):
                pass
            elif on_refusal is not None and isinstance(exc, TransportError):
                on_refusal(exc)
            else:
                raise
        delay = min(2 * delay, RETRY_MAX_S)


def check_zenoh_config(path: Path) -> None:
    """Read ``path`` as :func:`zenoh_config_text` does and, where zenoh is installed, parse it as
    zenoh will; ValueError with one line (without the path) for what ``mapd run`` would refuse."""
    text = zenoh_config_text(path)
    try:
        import zenoh
    except ImportError:  # the optional dependency: the file is read, its keys are zenoh's to judge
        return
    try:
        zenoh.Config.from_json5(text)
    except zenoh.ZError as exc:
        raise ValueError(zenoh_message(exc)) from None


#: The session keys a zenoh plugin's table holds, and where a zenoh config file holds each.
TABLE_KEYS = {
    "mode": "mode",
    "listen": "listen/endpoints",
    "connect": "connect/endpoints",
    "multicast_scouting": "scouting/multicast/enabled",
}


def table_keys_set(options: Any) -> set[str]:
    """The :data:`TABLE_KEYS` the table sets (an empty endpoint list sets nothing): with a config
    file, only these go over it; the others keep the file's value."""
    return {
        name for name in TABLE_KEYS if name in options.model_fields_set and getattr(options, name, []) != []
    }


def file_values(path: Path) -> dict[str, Any]:
    """The :data:`TABLE_KEYS` the zenoh config at ``path`` sets, with their values: those set to a
    value other than zenoh's default (a parsed config cannot tell one set to the default from one
    left out); none when it cannot be read (check_zenoh_config says why)."""
    try:
        import zenoh

        conf, default = zenoh.Config.from_json5(zenoh_config_text(path)), zenoh.Config()
    except Exception:
        return {}
    out = {}
    for name, key in TABLE_KEYS.items():
        try:
            theirs = json.loads(conf.get_json(key))
            if theirs != json.loads(default.get_json(key)):
                out[name] = theirs
        except Exception:  # a zenoh without the key: nothing to compare
            continue
    return out


def table_conflicts(options: Any, path: Path) -> list[str]:
    """The keys the table sets to other values than the zenoh config at ``path`` does, in words
    (a file that holds only TLS settings leaves mode and endpoints to the table)."""
    theirs = file_values(path)
    return [
        f"{name} {json.dumps(getattr(options, name))} here, {json.dumps(theirs[name])} there"
        for name in sorted(table_keys_set(options))
        if name in theirs and theirs[name] != getattr(options, name)
    ]


def check_tls(path: Path | None, listen: list[str], field: str = "config_file") -> None:
    """ValueError with one line for TLS files the zenoh config at ``path`` names that the session
    could not load, or a tls/quic listener in ``listen`` with none to listen with.

    A relative file name is looked up from the working directory, where zenoh looks (``/`` under
    systemd): in ``mapd run`` exactly, in ``mapd check-config`` as a ``mapd run`` started from the
    same folder would (a relative key that check-config passed stopped the start, where zenoh could
    not read it).
    """
    tls: dict[str, Any] = {}
    if path is not None:
        try:
            import zenoh
        except ImportError:  # the optional dependency: nothing opens a session either
            return
        try:
            conf = zenoh.Config.from_json5(zenoh_config_text(path))
            tls = json.loads(conf.get_json("transport/link/tls")) or {}
        except (zenoh.ZError, ValueError, TypeError):
            return  # said by the file's own check
        for key, marker in _TLS_FILES.items():
            name = tls.get(key)
            if not isinstance(name, str) or not name:
                continue
            problem = (
                _pem_problem(Path(name), marker) if Path(name).is_absolute() else _relative_pem(name, marker)
            )
            if problem:
                raise ValueError(f"{field}: {path}: transport.link.tls.{key}: {problem}")
    for ep in listen:
        proto = ep.partition("/")[0]
        if (
            proto in ("tls", "quic")
            and "#" not in ep
            and not (tls.get("listen_private_key") and tls.get("listen_certificate"))
        ):
            raise ValueError(
                f"listen: {ep}: a {proto} listener needs transport.link.tls.listen_private_key and "
                f"listen_certificate in a zenoh config ({field})"
            )


def _relative_pem(name: str, marker: str) -> str | None:
    """Why zenoh could not load relative ``name`` from the working directory, or None."""
    path, where = from_workdir(name)
    said = f"'{name}' is relative, so mapd run's zenoh session reads it from {where}"
    if path is None:
        return said
    problem = _pem_problem(path, marker)
    return f"{said}: {problem}" if problem else None


def _pem_problem(path: Path, marker: str) -> str | None:
    try:
        with open_regular(path) as fh:
            text = fh.read(_MAX_PEM).decode("ascii", "replace")
    except NotRegularFileError:
        return f"{path}: not a regular file"
    except OSError as exc:
        return f"{path}: cannot read it: {exc.strerror or exc}"
    if "-----BEGIN " not in text or marker not in text:
        what = "private key" if "KEY" in marker else "certificate"
        return f"{path}: holds no PEM {what}"
    return None


class ZenohConfigFiles:
    """For plugin options that name zenoh config files, in the fields ``beside_config`` lists.

    A relative path there is taken from the mapd config's folder, as ``robot.key_file`` is (under
    systemd the working directory is ``/``), and ``mapd check-config`` reads and parses each file
    (``check_files``), so a missing, malformed or non-regular one is caught before ``mapd run``,
    and so are the TLS key and certificate files it names (:func:`check_tls`).
    """

    beside_config: ClassVar[tuple[str, ...]] = ("config_file",)

    def check_files(self) -> None:
        """ValueError naming the option and the file, for a file ``mapd run`` would refuse."""
        for name in self.beside_config:
            path = getattr(self, name)
            if path is None:
                continue
            try:
                check_zenoh_config(path)
            except ValueError as exc:
                raise ValueError(f"{name}: {path}: {exc}") from None
            if conflicts := table_conflicts(self, path):
                # Set here, they went over the file: the example config's mode = "peer" and
                # multicast_scouting = true turned robot-tls.json5's TLS client into a peer that
                # scouts and listens on plain TCP, with no word.
                raise ValueError(
                    f"{name}: {path}: {'; '.join(conflicts)}: a key set in both must agree (set here, "
                    "it goes over the file); leave it out of one"
                )
        # The TLS files the config names, and a tls/quic listener without them: the session's
        # open refused those at start (every such options class has ``listen``).
        field = self.beside_config[0]
        check_tls(getattr(self, field), list(getattr(self, "listen", [])), field=field)
