"""The view's HTTP side, on a real socket: routes, token, viewer cap, SSE; and its ``[view]`` config."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest

from mapd import config as configmod
from mapd.config.endpoints import check_endpoints
from mapd.config.sections import split_listen
from mapd.errors import ConfigError, DaemonError
from mapd.grid import OccupancyGrid
from mapd.outputs.base import GlobalUpdate
from mapd.view.model import MapModel
from mapd.view.queue import sse
from mapd.view.server import KEEPALIVE_S, ViewServer

TOKEN = "s3cret-token-0123456789"


def serve(body: Callable[[ViewServer, str], Awaitable[None]], *, token: str | None = None, **kw: Any) -> None:
    """Run ``body(server, base_url)`` against a started server on an ephemeral loopback port."""

    async def main() -> None:
        server = ViewServer("127.0.0.1", 0, token=token, **kw)
        await server.start()
        try:
            await asyncio.wait_for(body(server, server.url), 30)
        finally:
            await server.close()

    asyncio.run(main())


async def events(resp: aiohttp.ClientResponse) -> AsyncIterator[tuple[str, dict[str, Any]]]:
    """Parse an SSE stream into (event, data) pairs."""
    kind = None
    async for raw in resp.content:
        line = raw.decode().rstrip("\n")
        if line.startswith("event: "):
            kind = line[len("event: ") :]
        elif line.startswith("data: ") and kind is not None:
            yield kind, json.loads(line[len("data: ") :])
            kind = None


def test_page_assets_and_404_for_everything_else() -> None:
    async def body(server: ViewServer, url: str) -> None:
        async with aiohttp.ClientSession() as s:
            async with s.get(url) as r:
                assert r.status == 200 and r.content_type == "text/html"
                page = await r.text()
                assert "static/view.js" in page and "__QUERY__" not in page and "token" not in page
                assert r.headers["Content-Security-Policy"].startswith("default-src 'self'")
            for asset, ctype in (("view.js", "text/javascript"), ("view.css", "text/css")):
                async with s.get(url + "static/" + asset) as r:
                    assert r.status == 200 and r.content_type == ctype and len(await r.read()) > 500
            for path in (
                "nope",
                "static/",
                "static/../live.py",
                "static/index.html",
                "events/x",
                "favicon.ico",
            ):
                async with s.get(url + path) as r:
                    assert r.status == 404, path
            async with s.post(url + "events") as r:
                assert r.status == 405  # read-only: nothing takes a POST

    serve(body)


def test_token_is_required_when_configured() -> None:
    async def body(server: ViewServer, url: str) -> None:
        async with aiohttp.ClientSession() as s:
            for path in ("", "static/view.js", "events", "nope"):
                async with s.get(url + path) as r:
                    assert r.status == 401, path
                async with s.get(url + path, params={"token": TOKEN + "x"}) as r:
                    assert r.status == 401, path
            async with s.get(url, params={"token": TOKEN}) as r:
                assert r.status == 200
                # the page hands the token on to its assets and its stream
                assert f"static/view.js?token={TOKEN}" in await r.text()
            async with s.get(url + "static/view.css", headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                assert r.status == 200
            # a page asked for with the header (a proxy adding it for its users) does not hold the
            # token: it was written into every such page, and into the proxy's log with each asset
            async with s.get(url, headers={"Authorization": f"Bearer {TOKEN}"}) as r:
                page = await r.text()
                assert r.status == 200 and TOKEN not in page and "static/view.js" in page
            # the scheme is case-insensitive (RFC 9110), the token is not
            async with s.get(url + "static/view.css", headers={"Authorization": f"bearer {TOKEN}"}) as r:
                assert r.status == 200
            async with s.get(
                url + "static/view.css", headers={"Authorization": f"Bearer {TOKEN.upper()}"}
            ) as r:
                assert r.status == 401
            async with s.get(url + "nope", params={"token": TOKEN}) as r:
                assert r.status == 404
        assert server.counters["refused_token"] == 9

    serve(body, token=TOKEN)


def test_viewers_past_the_cap_get_503_and_a_freed_place_is_reused() -> None:
    async def body(server: ViewServer, url: str) -> None:
        async with aiohttp.ClientSession() as s:
            a = await s.get(url + "events")
            b = await s.get(url + "events")
            assert a.status == b.status == 200
            await asyncio.sleep(0.05)
            assert server.viewers == 2
            async with s.get(url + "events") as r:
                assert r.status == 503 and "2 viewers" in await r.text()
            a.close()
            for _ in range(100):
                if server.viewers < 2:
                    break
                await asyncio.sleep(0.02)
            async with s.get(url + "events") as r:
                assert r.status == 200
            b.close()
        assert server.counters["refused_busy"] == 1

    serve(body, max_viewers=2)


def _grid(occupied_col: int | None = None) -> OccupancyGrid:
    d = np.zeros((100, 300), np.int8)
    if occupied_col is not None:
        d[40:60, occupied_col] = 100
    return OccupancyGrid(d, 0.05)


def test_sse_delivers_full_state_then_updates_and_status() -> None:
    snaps = {"robot": "r0", "fleet": "f", "links": {"zenoh": {"bytes_tx": 5, "bytes_rx": 1}}}

    async def body(server: ViewServer, url: str) -> None:
        model = MapModel()
        delta = model.global_map(GlobalUpdate(_grid(), {}, 1.0))
        server.post(delta, model.robots(), full_map=model.full_map())
        async with aiohttp.ClientSession() as s, s.get(url + "events") as r:
            assert r.status == 200 and r.content_type == "text/event-stream"
            it = events(r)
            hello = {
                "instance": server.instance,
                "status_every_s": server.status_every_s,
                "keepalive_s": KEEPALIVE_S,
            }
            assert await anext(it) == ("hello", hello)  # before any state
            kind, first = await anext(it)
            assert kind == "map" and first["full"] and first["seq"] == 1 and len(first["tiles"]) == 3
            seen = {kind}
            while seen != {"map", "robots", "status"}:
                kind, data = await anext(it)
                seen.add(kind)
            # a new map version arrives as a delta with only the changed tile
            delta = model.global_map(GlobalUpdate(_grid(occupied_col=200), {}, 2.0))
            server.post(delta, full_map=model.full_map())
            while True:
                kind, data = await anext(it)
                if kind == "map":
                    break
            assert data["seq"] == 2 and not data["full"] and [t[:2] for t in data["tiles"]] == [[1, -1]]

    serve(body, snapshot=lambda: snaps, status_every_s=0.05)


def test_a_viewer_that_stops_reading_does_not_hold_up_the_others() -> None:
    async def body(server: ViewServer, url: str) -> None:
        model = MapModel()
        rng = np.random.default_rng(1)
        async with aiohttp.ClientSession() as s:
            stuck = await s.get(url + "events")  # connected, never read
            async with s.get(url + "events") as r:
                it = events(r)
                for i in range(1, 60):
                    d = (rng.random((256, 256)) < 0.5).astype(np.int8) * 100  # ~40 kB of tiles each
                    delta = model.global_map(GlobalUpdate(OccupancyGrid(d, 0.05), {}, float(i)))
                    server.post(delta, sse("status", {"i": i}), full_map=model.full_map())
                    await asyncio.sleep(0)
                last = 0
                while last < model.seq:
                    kind, data = await anext(it)
                    if kind == "map":
                        last = data["seq"]
                assert last == model.seq
            assert server.counters["dropped_msgs"] > 0  # the stuck one skipped messages, bounded
            stuck.close()

    serve(body)


def test_a_port_in_use_is_one_daemon_error() -> None:
    async def body(server: ViewServer, url: str) -> None:
        other = ViewServer("127.0.0.1", server.port)
        with pytest.raises(DaemonError, match=r"view: cannot listen on 127\.0\.0\.1:\d+"):
            await other.start()

    serve(body)


# ---------------------------------------------------------------------------- [view] in config.toml


def _config(tmp_path: Path, view: str) -> Path:
    p = tmp_path / "config.toml"
    p.write_text(
        f'[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n'
        f'[state]\ndir = "{tmp_path / "state"}"\nruntime_dir = "{tmp_path / "run"}"\n[view]\n{view}\n'
    )
    return p


def test_config_refuses_non_loopback_without_a_token_in_one_line(tmp_path: Path) -> None:
    cfg = configmod.load(_config(tmp_path, 'listen = "0.0.0.0:8080"'))
    with pytest.raises(ConfigError) as err:
        configmod.check(cfg)
    msg = str(err.value)
    assert "\n" not in msg and "view.token_file" in msg and "0.0.0.0:8080" in msg and "loopback" in msg


@pytest.mark.parametrize("listen", ["127.0.0.1:8080", "localhost:8080", "[::1]:8080", "127.0.0.5:1"])
def test_config_allows_loopback_without_a_token(tmp_path: Path, listen: str) -> None:
    checked = configmod.check(configmod.load(_config(tmp_path, f'listen = "{listen}"')))
    assert checked.view_token is None


def test_config_reads_the_token_file_relative_to_the_config(tmp_path: Path) -> None:
    (tmp_path / "view.token").write_text(TOKEN + "\n")
    cfg = configmod.load(_config(tmp_path, 'listen = "0.0.0.0:8080"\ntoken_file = "view.token"'))
    assert configmod.check(cfg).view_token == TOKEN
    (tmp_path / "view.token").write_text("short\n")
    with pytest.raises(ConfigError, match="must hold one token of 16\\+ characters"):
        configmod.check(cfg)


@pytest.mark.parametrize("char", ["+", "&", "#", "%", "/", "=", "?", ";", '"', "<"])
def test_config_refuses_a_token_the_url_would_change(tmp_path: Path, char: str) -> None:
    """The README's ``?token=<token>``, pasted as is: ``+`` arrives as a space, ``&`` and ``#`` end it,
    ``%`` escapes what follows; so only characters a URL carries unchanged are taken."""
    (tmp_path / "view.token").write_text(f"0123456789{char}abcdefgh\n")
    cfg = configmod.load(_config(tmp_path, 'listen = "0.0.0.0:8080"\ntoken_file = "view.token"'))
    with pytest.raises(ConfigError) as err:
        configmod.check(cfg)
    msg = str(err.value)
    assert "\n" not in msg and "view.token_file" in msg and "openssl rand -hex 24" in msg
    assert "A-Z a-z 0-9" in msg


def test_a_url_safe_token_works_pasted_raw_into_the_url(tmp_path: Path) -> None:
    token = "Ab9._~-Zz0123456789-openssl-rand-hex"
    (tmp_path / "view.token").write_text(token + "\n")
    cfg = configmod.load(_config(tmp_path, 'listen = "0.0.0.0:8080"\ntoken_file = "view.token"'))
    assert configmod.check(cfg).view_token == token

    async def body(server: ViewServer, url: str) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(f"GET /?token={token} HTTP/1.1\r\nHost: robot\r\nConnection: close\r\n\r\n".encode())
        answer = await reader.read()
        writer.close()
        assert answer.startswith(b"HTTP/1.1 200 "), answer[:80]

    serve(body, token=token)


@pytest.mark.parametrize(
    "listen",
    ["8080", "127.0.0.1", "127.0.0.1:0", "127.0.0.1:99999", ":80", "::1:8080", "[::1:8080", "::1]:8080"],
)
def test_config_refuses_a_malformed_listen(tmp_path: Path, listen: str) -> None:
    with pytest.raises(ConfigError, match=r"view\.listen"):
        configmod.load(_config(tmp_path, f'listen = "{listen}"'))


@pytest.mark.parametrize(
    "address", ["[::1]:8080", "127.0.0.1:8080", "::1:8080", "[::1:8080", "::1]:8080", "h:x"]
)
def test_the_view_and_zenoh_read_host_port_alike(address: str) -> None:
    """One reading of HOST:PORT: before, the view split ``::1:8080`` at its last colon (a zenoh
    endpoint refused it for want of brackets), so the same address passed in one option and not in
    the other."""

    def taken(check: Callable[[], object]) -> bool:
        try:
            check()
        except ValueError:
            return False
        return True

    assert taken(lambda: split_listen(address)) == taken(lambda: check_endpoints([f"tcp/{address}"]))


def test_view_is_off_by_default(tmp_path: Path) -> None:
    cfg = configmod.load(_config(tmp_path, ""))
    assert cfg.view.listen is None and configmod.check(cfg).view_token is None


def test_each_stream_starts_with_the_servers_instance_new_at_every_start() -> None:
    """A page that reconnects to a restarted daemon learns it from the hello (and drops the old map)."""
    seen: list[str] = []

    async def body(server: ViewServer, url: str) -> None:
        async with aiohttp.ClientSession() as s:
            for _ in range(2):
                async with s.get(url + "events") as r:
                    kind, data = await anext(events(r))
                    assert kind == "hello" and data["instance"] == server.instance
        seen.append(server.instance)

    serve(body)
    serve(body)
    assert len(seen) == 2 and seen[0] != seen[1] and all(len(i) >= 16 for i in seen)


def test_a_new_token_is_in_force_at_once_and_ends_the_streams_of_the_old_one() -> None:
    """What a reload does with a rotated token (``set_token``): the old one is refused from the next
    request on, and a stream it opened ends instead of watching on."""
    new = "n3w-token-9876543210"

    async def body(server: ViewServer, url: str) -> None:
        async with aiohttp.ClientSession() as s:
            stream = await s.get(url + "events", params={"token": TOKEN})
            assert stream.status == 200
            assert (await anext(events(stream)))[0] == "hello"
            assert server.set_token(TOKEN) is False  # the same token: nothing ends
            assert server.viewers == 1
            assert server.set_token(new) is True
            rest = await asyncio.wait_for(stream.read(), 10)  # the stream ends (before: never)
            assert b"event: hello" not in rest
            stream.close()
            for token, status in ((TOKEN, 401), (new, 200)):
                async with s.get(url, params={"token": token}) as r:
                    assert r.status == status, token
                    if status == 200:  # the page hands on the token now in force
                        assert f"?token={new}" in await r.text()
                async with s.get(url + "static/view.css", headers={"Authorization": f"Bearer {token}"}) as r:
                    assert r.status == status, token
        assert server.viewers == 0

    serve(body, token=TOKEN)
