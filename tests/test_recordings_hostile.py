"""Issue 26, defect 5: a recording download is bound to the session's host like every RPC, a
symbolic link in the recordings folder is no recording, ``Range: bytes=-0`` is 416, and the
``/commands`` channel records the sender's station id, never its session token."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path

import aiohttp
import pytest
from conftest import quiet_platform_config, wait_until
from support.recorder import recorder_of
from support.velocity import open_connection

from brasidas.admission import SourceLedger
from brasidas.messages import CommandReceived
from brasidas.recording import schemas
from platformd.app import PlatformDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]


async def test_downloads_are_bound_to_the_sessions_host_and_refuse_links_and_empty_ranges(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    recordings = tmp_path / "recordings"
    daemon = await platform_factory(
        quiet_platform_config("recorder.enabled=true", f"recorder.dir={recordings}"), fleet_key
    )
    recorder = recorder_of(daemon)
    await wait_until(lambda: bool(recorder.writer.stats.current), 10)
    name = recorder.writer.stats.current
    secret = tmp_path / "fleet.key"
    secret.write_bytes(b"the fleet key")
    planted = "2020-01-01T00-00-00Z.mcap"
    (recordings / planted).symlink_to(secret)
    conn = await open_connection(daemon, fleet_key)  # from 127.0.0.1
    url = f"{daemon.ctx.signaling_url}/recordings"
    token = {"X-Brasidas-Session": conn.session_id}
    try:
        async with aiohttp.ClientSession() as http:
            async with http.get(f"{url}/{name}", headers=token) as response:
                assert response.status == 200  # the session's own host
            async with http.get(f"{url}/{planted}", headers=token) as response:
                assert response.status == 404
                assert b"fleet key" not in await response.read()
            async with http.get(f"{url}/{name}", headers={**token, "Range": "bytes=-0"}) as r:
                assert r.status == 416
                assert r.headers["Content-Range"].startswith("bytes */")
        # The token lifted off the air, used from another host: refused.
        other = aiohttp.TCPConnector(local_addr=("127.0.0.2", 0))
        async with aiohttp.ClientSession(connector=other) as http:
            async with http.get(f"{url}/{name}", headers=token) as response:
                assert response.status == 401
                assert "another host" in await response.text()
    finally:
        await conn.close()


def test_the_commands_channel_records_the_station_never_the_token() -> None:
    token = "3q2+7w-session-token-abcdef"
    for payload in ("on", json.dumps({"session": token, "waypoints": []})):
        command = CommandReceived("rpc", "set_waypoints", payload, token, "ops-1", True)
        record = json.loads(schemas.encode_command(command))
        assert token not in json.dumps(record)
        assert record["station"] == "ops-1"
    assert "session" not in schemas.COMMAND["properties"]


def test_parallel_downloads_share_one_rate() -> None:
    ledger = SourceLedger(download_rate=1024 * 1024)  # 1 MiB/s for everyone together
    delays = [ledger.reserve_download("10.0.0.1", 64 * 1024, 10.0) for _ in range(16)]
    assert delays[0] == 0
    assert delays[-1] == pytest.approx(15 / 16)  # one host's 16 downloads
    assert ledger.reserve_download("10.0.0.1", 64 * 1024, 12.0) == 0  # idle since: no debt
    assert SourceLedger().reserve_download("10.0.0.1", 10**9, 0.0) == 0  # 0: no limit
