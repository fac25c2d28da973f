"""zenoh's own TLS, mutual TLS and access control, with the example configs in deploy/zenoh/.

Real zenoh sessions on loopback (free ports, multicast scouting off): a router opened from
``router-tls.json5`` and robots from ``robot-tls.json5``, each "machine" with its own copy of
``/etc/mapd/tls/`` made here with ``cryptography`` (a fleet CA, the router's and robots'
certificates, and a second CA for outsiders). Shows that

* robots holding fleet certificates connect over ``tls/`` and mapd's ZenohTransport, pointed at
  the example with ``config_file``, exchanges signed maps, presence, keyframe queries and acks
  through the router with its ACL on;
* a client without a certificate, with one from another CA, or speaking plain TCP cannot open a
  session; a peer that cannot connect sees no map; a robot refuses a router whose certificate the
  fleet CA did not sign;
* the router's ACL passes ``mapd/<fleet>/**`` and drops any other key (and with the ACL turned
  off the same keys do pass, so the ACL is what stops them).
"""

from __future__ import annotations

import asyncio
import datetime
import ipaddress
import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from mapd.demo.ports import free_port
from mapd.envelope import Envelope, unpack
from mapd.errors import TransportError
from mapd.grid import Pose2D
from mapd.identity import Identity, Roster
from transports.base import Delivered, KeyframeNeeded, PeerUp, Received, TransportContext, TransportEvent
from transports.zenoh.link import ZenohTransport

zenoh: Any = pytest.importorskip("zenoh")

EXAMPLES = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
#: The fleet id written in the example router's ACL rule (mapd/myfleet/**).
FLEET = "myfleet"
#: Where the examples expect the certificates; each test machine gets its own copy of this folder.
TLS_DIR = "/etc/mapd/tls/"


def _tls_missing() -> str | None:
    """Why this zenoh build cannot do TLS, or None when it can."""
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", '["tls/127.0.0.1:0"]')
    try:
        zenoh.open(conf).close()  # pragma: no cover - without a key this never opens
    except zenoh.ZError as exc:
        if "not supported" in str(exc).lower():
            return f"this eclipse-zenoh build has no TLS transport: {exc}"
    return None


_MISSING = _tls_missing()
pytestmark = pytest.mark.skipif(_MISSING is not None, reason=_MISSING or "")


# --- certificates ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Issued:
    """A private key and its certificate."""

    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def make_ca(cn: str) -> Issued:
    """A self-signed CA (what `openssl req -x509` makes in docs/zenoh.md)."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(_name(cn))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return Issued(key, cert)


def issue(ca: Issued, cn: str, *, dns: tuple[str, ...] = (), ips: tuple[str, ...] = ()) -> Issued:
    """A leaf certificate for ``cn`` signed by ``ca``, good as TLS server and client."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    sans: list[x509.GeneralName] = [x509.DNSName(d) for d in dns or (cn,)]
    sans += [x509.IPAddress(ipaddress.ip_address(ip)) for ip in ips]
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(ca.cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()), critical=False
        )
        .sign(ca.key, hashes.SHA256())
    )
    return Issued(key, cert)


@dataclass(frozen=True)
class Pki:
    """The fleet CA and its router and robot certificates, plus an outsider's CA and certificate."""

    ca: Issued
    router: Issued
    robots: dict[str, Issued]
    other_ca: Issued
    outsider: Issued
    #: A router certificate for 127.0.0.1 from the other CA (an impostor router).
    impostor: Issued


@pytest.fixture(scope="module")
def pki() -> Pki:
    ca, other = make_ca("myfleet fleet CA"), make_ca("someone else's CA")
    return Pki(
        ca=ca,
        router=issue(ca, "zenoh-router.lan", dns=("zenoh-router.lan",), ips=("127.0.0.1",)),
        robots={r: issue(ca, r) for r in ("r1", "r2")},
        other_ca=other,
        outsider=issue(other, "r1"),
        impostor=issue(other, "zenoh-router.lan", dns=("zenoh-router.lan",), ips=("127.0.0.1",)),
    )


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def install(machine: Path, ca: x509.Certificate, stem: str, own: Issued) -> Path:
    """``machine``'s ``/etc/mapd/tls``: ca.pem, ``stem``.pem and ``stem``.key (0600)."""
    tls = machine / "tls"
    tls.mkdir(parents=True)
    (tls / "ca.pem").write_bytes(_pem(ca))
    (tls / f"{stem}.pem").write_bytes(_pem(own.cert))
    key = tls / f"{stem}.key"
    key.write_bytes(
        own.key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    key.chmod(0o600)
    return tls


def example(name: str, machine: Path, tls: Path) -> Path:
    """A copy of deploy/zenoh/``name`` for ``machine``, its certificate paths pointing at ``tls``."""
    text = (EXAMPLES / name).read_text()
    assert TLS_DIR in text
    out = machine / name
    out.write_text(text.replace(TLS_DIR, f"{tls}/"))
    return out


# --- zenoh sessions --------------------------------------------------------------------------


def open_from(path: Path, **settings: Any) -> Any:
    """A zenoh session from the config file ``path`` with ``settings`` (zenoh key path with ``/``
    written as ``__``) inserted over it."""
    conf = zenoh.Config.from_file(str(path))
    for key, value in settings.items():
        conf.insert_json5(key.replace("__", "/"), json.dumps(value))
    return zenoh.open(conf)


@contextmanager
def router(
    tmp: Path,
    pki: Pki,
    *,
    acl: bool = True,
    own: Issued | None = None,
    settings: dict[str, Any] | None = None,
) -> Iterator[str]:
    """The example router on ``tls/127.0.0.1:<free port>``, as written (or with its ACL turned off,
    or ``settings`` inserted as in :func:`open_from`); yields that endpoint."""
    tls = install(tmp / "router", pki.ca.cert, "router", own or pki.router)
    conf = example("router-tls.json5", tmp / "router", tls)
    ep = f"tls/127.0.0.1:{free_port()}"
    off = {} if acl else {"access_control__enabled": False}
    session = open_from(conf, listen__endpoints=[ep], **off, **(settings or {}))
    try:
        yield ep
    finally:
        session.close()


def robot_config(tmp: Path, pki: Pki, robot: str, own: Issued | None = None) -> Path:
    """The example robot config on ``robot``'s own machine, with its certificate (or ``own``)."""
    machine = tmp / robot
    tls = install(machine, pki.ca.cert, "robot", own or pki.robots[robot])
    return example("robot-tls.json5", machine, tls)


@contextmanager
def robot_session(tmp: Path, pki: Pki, robot: str, ep: str) -> Iterator[Any]:
    """A plain zenoh session opened from the example robot config, connected to ``ep``."""
    session = open_from(robot_config(tmp, pki, robot), connect__endpoints=[ep])
    try:
        yield session
    finally:
        session.close()


def wait_until(cond: Callable[[], bool], timeout: float = 5.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"{what} not met within {timeout} s"
        time.sleep(0.02)


# --- the example files -----------------------------------------------------------------------


def test_example_configs_load_with_the_tls_and_acl_keys_set() -> None:
    def get(conf: Any, key: str) -> Any:
        return json.loads(conf.get_json(key))

    r = zenoh.Config.from_file(str(EXAMPLES / "router-tls.json5"))
    assert get(r, "mode") == "router"
    assert get(r, "listen/endpoints") == ["tls/0.0.0.0:7447"]
    assert get(r, "transport/link/tls/enable_mtls") is True
    assert get(r, "transport/link/tls/root_ca_certificate") == "/etc/mapd/tls/ca.pem"
    assert get(r, "transport/link/tls/listen_certificate") == "/etc/mapd/tls/router.pem"
    assert get(r, "transport/link/tls/listen_private_key") == "/etc/mapd/tls/router.key"
    acl = get(r, "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert [rule["key_exprs"] for rule in acl["rules"]] == [[f"mapd/{FLEET}/**"], ["mapd/@fleets/**"]]
    assert acl["rules"][1]["messages"] == [
        "liveliness_token",
        "liveliness_query",
        "declare_liveliness_subscriber",
    ]

    b = zenoh.Config.from_file(str(EXAMPLES / "robot-tls.json5"))
    assert get(b, "mode") == "client"
    assert all(ep.startswith("tls/") for ep in get(b, "connect/endpoints"))
    assert get(b, "scouting/multicast/enabled") is False
    assert get(b, "transport/link/tls/enable_mtls") is True
    assert get(b, "transport/link/tls/connect_certificate") == "/etc/mapd/tls/robot.pem"
    assert get(b, "transport/link/tls/connect_private_key") == "/etc/mapd/tls/robot.key"
    assert get(b, "transport/link/tls/verify_name_on_connect") is True


# --- (a) fleet certificates: mapd over tls/ through the router with its ACL ----------------------


class Robot:
    """mapd's ZenohTransport for ``robot``, configured only by ``config_file`` plus the router's
    test endpoint (as a user would set ``[transports.zenoh] config_file``)."""

    def __init__(self, config: Path, robot: str, ep: str, ids: dict[str, Identity]) -> None:
        self.events: list[TransportEvent] = []
        self.keyframe: Envelope | None = None
        self.roster = Roster({r: i.public_key for r, i in ids.items()})
        self.ctx = TransportContext(
            robot=robot,
            fleet=FLEET,
            max_message_bytes=1 << 20,
            emit=self.events.append,
            identity=ids[robot],
            roster=self.roster,
            latest_keyframe=lambda: self.keyframe,
        )
        self.t = ZenohTransport(ZenohTransport.Options(config_file=config, connect=[ep]), self.ctx)

    def offer(self, env: Envelope) -> None:
        if env.is_keyframe:
            self.keyframe = env
        self.t.offer(env)

    def of(self, kind: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    async def wait(self, cond: Callable[[], bool], timeout: float = 5.0) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(
                    f"{self.ctx.robot}: not met in {timeout} s: {self.events} {self.t.stats()}"
                )
            await asyncio.sleep(0.01)


def envelope(ident: Identity, version: int, base: int = 0) -> Envelope:
    return Envelope(
        fleet=FLEET,
        robot=ident.robot,
        version=version,
        base_version=base,
        codec="raw",
        width=4,
        height=3,
        resolution=0.05,
        origin=Pose2D(0.0, 0.0, 0.0),
        payload=bytes(range(12)),
        seq=version,
    ).signed(ident)


def test_fleet_robots_share_signed_maps_over_mtls_through_the_acl_router(tmp_path: Path, pki: Pki) -> None:
    ids = {r: Identity.generate(r) for r in pki.robots}

    async def main(ep: str) -> None:
        r1 = Robot(robot_config(tmp_path, pki, "r1"), "r1", ep, ids)
        r2 = Robot(robot_config(tmp_path, pki, "r2"), "r2", ep, ids)
        try:
            await r1.t.start()
            r1.offer(envelope(ids["r1"], 1))  # nobody hears it: r2 is not there yet
            # put before r2 starts (on a loaded machine the outbox may lag: r2 would then hear the
            # put itself and not ask, and the late-join query below would never come)
            await r1.wait(lambda: r1.t.stats()["updates_tx"] == 1)
            await r2.t.start()
            # Presence (liveliness) both ways, and r2's late-join query answered with r1's keyframe.
            await r1.wait(lambda: PeerUp("zenoh", "r2") in r1.events)
            await r2.wait(lambda: PeerUp("zenoh", "r1") in r2.events)
            await r2.wait(lambda: bool(r2.of(Received)))
            await r1.wait(lambda: KeyframeNeeded("zenoh", "r2", "r1") in r1.events)
            # A delta on it arrives as a put, signed end to end (zenoh's TLS ends at the router).
            r1.offer(envelope(ids["r1"], 2, 1))
            await r2.wait(lambda: len(r2.of(Received)) == 2)
            got = [unpack(e.data, roster=r2.roster, fleet=FLEET) for e in r2.of(Received)]
            assert [(g.robot, g.version, g.base_version) for g in got] == [("r1", 1, 0), ("r1", 2, 1)]
            # The ack goes back through the router too.
            r2.t.ack("r1", 2)
            await r1.wait(lambda: bool(r1.of(Delivered)))
            assert r1.of(Delivered) == [Delivered("zenoh", "r2", "r1", 2)]
            assert r1.t.stats()["errors"] == 0 and r2.t.stats()["bad_signature"] == 0
        finally:
            await r2.t.close()
            await r1.t.close()

    with router(tmp_path, pki) as ep:
        asyncio.run(asyncio.wait_for(main(ep), 20))


# --- (b) outsiders cannot join -----------------------------------------------------------------


def _outsider_settings(pki: Pki, tmp: Path, how: str, ep: str) -> tuple[Path, dict[str, Any]]:
    """The example robot config on an outsider's machine, and what the outsider changes in it."""
    config = robot_config(tmp, pki, "outsider", own=pki.outsider)
    if how == "no client certificate":
        return config, {"connect__endpoints": [ep], "transport__link__tls__enable_mtls": False}
    if how == "certificate from another CA":
        return config, {"connect__endpoints": [ep]}
    assert how == "plain tcp to the tls port"
    return config, {"connect__endpoints": [ep.replace("tls/", "tcp/")]}


@pytest.mark.parametrize(
    "how", ["no client certificate", "certificate from another CA", "plain tcp to the tls port"]
)
def test_a_client_without_a_fleet_certificate_cannot_open_a_session(
    tmp_path: Path, pki: Pki, how: str
) -> None:
    with router(tmp_path, pki) as ep:
        config, settings = _outsider_settings(pki, tmp_path, how, ep)
        with pytest.raises(zenoh.ZError, match="Unable to connect"):
            open_from(config, **settings).close()


def test_mapd_reports_a_refused_certificate_in_one_line(tmp_path: Path, pki: Pki) -> None:
    with router(tmp_path, pki) as ep:
        config = robot_config(tmp_path, pki, "outsider", own=pki.outsider)
        ctx = TransportContext(robot="r1", fleet=FLEET, max_message_bytes=1 << 20, emit=lambda e: None)
        t = ZenohTransport(ZenohTransport.Options(config_file=config, connect=[ep]), ctx)

        async def main() -> None:
            try:
                with pytest.raises(
                    TransportError, match=r"^zenoh: cannot open session: Unable to connect"
                ) as err:
                    await t.start()
                assert "\n" not in str(err.value), str(err.value)
            finally:
                await t.close()

        asyncio.run(asyncio.wait_for(main(), 10))


def test_a_peer_without_a_fleet_certificate_sees_no_map(tmp_path: Path, pki: Pki) -> None:
    """In peer mode zenoh opens a session even when no connection succeeds: it just hears nothing."""
    key = f"mapd/{FLEET}/r1/update"
    with router(tmp_path, pki) as ep:
        config, settings = _outsider_settings(pki, tmp_path, "no client certificate", ep)
        outsider = open_from(config, mode="peer", **settings)
        heard: list[str] = []
        got: list[str] = []
        try:
            outsider.declare_subscriber(f"mapd/{FLEET}/**", lambda s: heard.append(str(s.key_expr)))
            with robot_session(tmp_path, pki, "r1", ep) as r1, robot_session(tmp_path, pki, "r2", ep) as r2:
                r2.declare_subscriber(f"mapd/{FLEET}/**", lambda s: got.append(str(s.key_expr)))

                def arrived() -> bool:
                    r1.put(key, b"map")
                    return bool(got)

                wait_until(arrived, what="a fleet robot hears the map")
                time.sleep(0.3)
        finally:
            outsider.close()
        assert got and heard == []


def test_a_robot_refuses_a_router_the_fleet_ca_did_not_sign(tmp_path: Path, pki: Pki) -> None:
    with (
        router(tmp_path, pki, own=pki.impostor) as ep,
        pytest.raises(zenoh.ZError, match="Unable to connect"),
    ):
        open_from(robot_config(tmp_path, pki, "r1"), connect__endpoints=[ep]).close()


# --- (c) the ACL fences the key space --------------------------------------------------------


@pytest.mark.parametrize("acl", [True, False], ids=["acl on", "acl off"])
def test_the_router_acl_passes_only_the_fleet_key_space(tmp_path: Path, pki: Pki, acl: bool) -> None:
    allowed = f"mapd/{FLEET}/r1/update"
    fenced = ["mapd/otherfleet/r1/update", "robots/r1/cmd_vel"]
    got: list[str] = []
    with (
        router(tmp_path, pki, acl=acl) as ep,
        robot_session(tmp_path, pki, "r1", ep) as r1,
        robot_session(tmp_path, pki, "r2", ep) as r2,
    ):
        for sub in (f"mapd/{FLEET}/**", "mapd/otherfleet/**", "robots/**"):
            r2.declare_subscriber(sub, lambda s: got.append(str(s.key_expr)))

        def arrived() -> bool:
            # The fenced keys go first on the same link: had they passed, they would arrive first.
            for key in [*fenced, allowed]:
                r1.put(key, b"x")
            return allowed in got

        wait_until(arrived, what=f"{allowed} arrives")
        time.sleep(0.3)
    assert allowed in got
    if acl:
        assert set(got) == {allowed}
    else:
        assert set(got) == {allowed, *fenced}


@pytest.mark.parametrize("presence_rule", [True, False], ids=["as written", "without the presence rule"])
def test_a_certificate_holder_of_another_fleet_id_is_said_and_hears_no_map(
    tmp_path: Path, pki: Pki, presence_rule: bool
) -> None:
    """A robot given a fleet certificate but another ``robot.fleet``: the example router lets the
    fleets' presence tokens through (``mapd/@fleets/**``), so each robot shows the other's fleet,
    and nothing more: the stray robot hears no map. Without that rule the ACL drops the tokens too
    and each robot runs alone, saying nothing (what the example did before the rule)."""
    ids = {"r1": Identity.generate("r1")}
    stray_ctx = TransportContext(
        robot="r2", fleet="otherfleet", max_message_bytes=1 << 20, emit=lambda e: None
    )

    async def main(ep: str) -> None:
        ours = Robot(robot_config(tmp_path, pki, "r1"), "r1", ep, ids)
        stray = ZenohTransport(
            ZenohTransport.Options(config_file=robot_config(tmp_path, pki, "r2"), connect=[ep]), stray_ctx
        )
        try:
            await ours.t.start()
            await stray.start()
            ours.offer(envelope(ids["r1"], 1))
            await ours.wait(lambda: ours.t.stats()["updates_tx"] == 1)
            if presence_rule:
                await ours.wait(lambda: ours.t.stats()["other_fleets"] == {"otherfleet": ["r2"]})
                await ours.wait(lambda: stray.stats()["other_fleets"] == {FLEET: ["r1"]})
            else:
                await asyncio.sleep(1.0)
                assert ours.t.stats()["other_fleets"] == {} and stray.stats()["other_fleets"] == {}
            assert stray.stats()["bytes_rx"] == 0 and stray.stats()["updates_rx"] == 0
        finally:
            await stray.close()
            await ours.t.close()

    # zenoh's ACL policy naming only the fleet's own rule: the example as it was before.
    before = {"access_control__policies": [{"rules": ["mapd-fleet"], "subjects": ["fleet-robots"]}]}
    with router(tmp_path, pki, settings={} if presence_rule else before) as ep:
        asyncio.run(asyncio.wait_for(main(ep), 20))
