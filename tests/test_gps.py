"""GPS: real receiver logs through a pty against gpsd's reference fixes; bad input; lost ports."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import tty
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brasidas import topics
from brasidas.bus import Bus
from brasidas.clock import ManualClock
from brasidas.codecs.nmea import EpochAssembler, NmeaDecoder, sentence
from brasidas.config import GpsSection
from brasidas.messages import GpsFix, GpsFixLost, GpsStats, Position
from platformd.gps import GpsReader
from tests.conftest import hang_serial_opens, record_loop_gaps, wait_until

NMEA = Path(__file__).resolve().parents[1].parent / "shared" / "testdata" / "nmea"
"""Receiver logs beside the repository (``../shared/testdata/nmea``)."""
LOGS = ["ublox-lea-5h", "ublox-8", "haicom-305N"]


class Pty:
    """A pseudo-terminal: the test writes the receiver's side (master), the reader opens ``path``."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        os.set_blocking(self.master, False)

    async def write(self, data: bytes) -> None:
        """Write everything, waiting (without blocking the loop) while the pty buffer is full."""
        loop = asyncio.get_running_loop()
        view = memoryview(data)
        while view:
            try:
                written = os.write(self.master, view)
            except BlockingIOError:
                ready = loop.create_future()
                loop.add_writer(self.master, ready.set_result, None)
                try:
                    await ready
                finally:
                    loop.remove_writer(self.master)
                continue
            view = view[written:]

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def receiver_lines(name: str) -> list[bytes]:
    """What the receiver sent: every line of the log except ``#`` comments, bytes untouched."""
    raw = (NMEA / f"{name}.log").read_bytes()
    return [line for line in raw.splitlines(keepends=True) if not line.startswith(b"#")]


def reference_fixes(name: str) -> list[tuple[str, float, float]]:
    """gpsd's TPV reports with a position, one per epoch (time of day, lat, lon)."""
    fixes: dict[str, tuple[float, float]] = {}
    for line in (NMEA / f"{name}.log.chk").read_text().splitlines():
        if not line.startswith("{"):
            continue
        report = json.loads(line)
        if report.get("class") == "TPV" and "lat" in report:
            fixes.setdefault(report["time"][11:23], (report["lat"], report["lon"]))
    return [(when, lat, lon) for when, (lat, lon) in fixes.items()]


class Recorder:
    def __init__(self, bus: Bus) -> None:
        self.fixes: list[GpsFix] = []
        self.lost: list[GpsFixLost] = []
        self.stats: list[GpsStats] = []
        self.positions: list[Position] = []
        bus.subscribe(topics.GPS_FIX, self.fixes.append)
        bus.subscribe(topics.GPS_FIX_LOST, self.lost.append)
        bus.subscribe(topics.GPS_STATS, self.stats.append)
        bus.subscribe(topics.POSITION, self.positions.append)


async def advancing(clock: ManualClock, predicate: Callable[[], bool]) -> None:
    """Let ``clock`` run (0.1 s a step, the loop turning between steps) until ``predicate``."""
    async with asyncio.timeout(5.0):
        while not predicate():
            clock.advance(0.1)
            await asyncio.sleep(0.002)


@contextlib.asynccontextmanager
async def running(reader: GpsReader) -> AsyncIterator[GpsReader]:
    task = asyncio.create_task(reader.run(), name="test:gps")
    try:
        yield reader
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@pytest.fixture
async def pty() -> AsyncIterator[Pty]:
    device = Pty()
    yield device
    device.close()


@pytest.mark.parametrize("name", LOGS)
async def test_real_log_through_pty_matches_reference(name: str, pty: Pty) -> None:
    bus = Bus()
    seen = Recorder(bus)
    reader = GpsReader(bus, GpsSection(port=pty.path))
    expected = reference_fixes(name)
    async with running(reader):
        await wait_until(lambda: reader.connected)
        for line in receiver_lines(name):
            await pty.write(line)
            await asyncio.sleep(0)
        # The last epoch has no cycle ender in the log: it is published once the line is quiet.
        await wait_until(lambda: len(seen.fixes) >= len(expected) and not reader.assembler.pending)
        await asyncio.sleep(0.1)
    assert len(seen.fixes) == len(expected)
    for fix, (when, lat, lon) in zip(seen.fixes, expected, strict=True):
        assert fix.time[-13:-1] == when
        assert fix.latitude == pytest.approx(lat, abs=1e-6)
        assert fix.longitude == pytest.approx(lon, abs=1e-6)
    assert seen.positions[-1] == Position(seen.fixes[-1].latitude, seen.fixes[-1].longitude)


async def test_fix_fields_from_one_epoch() -> None:
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    out = []
    lines = receiver_lines("ublox-8")[:40]
    for line in lines:
        for parsed in decoder.feed(line):
            out += assembler.feed(parsed, 0.0)
    first = out[0]
    assert first is not None
    assert first.time == "2017-01-10T00:09:41.000Z"
    assert first.altitude_m == pytest.approx(1144.8)
    assert first.satellites == 12
    assert first.hdop == pytest.approx(1.01)
    assert first.quality == 1
    assert first.speed_mps == pytest.approx(0.029 * 1852 / 3600)
    assert decoder.dropped["noise"] == 1  # the UBX binary in front of the first $GNRMC
    assert decoder.by_type["GSV"] == sum(b"GSV," in line for line in lines)
    assert decoder.by_type["ZDA"] == sum(b"ZDA," in line for line in lines)


async def test_garbage_dropped_and_counted(pty: Pty) -> None:
    bus = Bus()
    seen = Recorder(bus)
    clock = ManualClock()
    reader = GpsReader(bus, GpsSection(port=pty.path), clock=clock)
    rmc = "GPRMC,120000.00,A,3756.49000,N,02339.18000,E,0.10,45.0,231126,,,A"
    gga = "GPGGA,120000.00,3756.49000,N,02339.18000,E,1,09,0.95,42.0,M,34.0,M,,"
    bad_checksum = sentence(rmc).replace(b"*", b"0*")  # body changed, old checksum
    async with running(reader):
        await wait_until(lambda: reader.connected)
        await pty.write(os.urandom(64).replace(b"\n", b"").replace(b"$", b"") + b"\r\n")
        await pty.write(bad_checksum)
        await pty.write(b"$GPGGA,120000.00,3756.49\r\n")  # truncated
        await pty.write(sentence("GPXYZ,1,2,3"))  # well formed, unknown type
        await pty.write(b"\x00\xff\xb5b" + sentence(rmc))  # noise glued in front of a sentence
        await pty.write(sentence(gga))
        await wait_until(lambda: reader.decoder.sentences == 2)
        # The first fix waits for the end of the receiver's cycle; the counters go out once
        # a second: both are the clock's business.
        await advancing(clock, lambda: bool(seen.stats) and seen.stats[-1].sentences == 2)
        assert len(seen.fixes) == 1
    dropped = seen.stats[-1].dropped
    assert dropped == {"checksum": 1, "malformed": 1, "unknown": 1, "noise": 2}
    assert seen.stats[-1].by_type == {"RMC": 1, "GGA": 1}
    fix = seen.fixes[0]
    assert fix.latitude == pytest.approx(37.9415)
    assert fix.longitude == pytest.approx(23.653)
    assert fix.satellites == 9
    assert fix.course_deg == pytest.approx(45.0)


async def test_no_fix_sentences_report_fix_lost(pty: Pty) -> None:
    bus = Bus()
    seen = Recorder(bus)
    reader = GpsReader(bus, GpsSection(port=pty.path))
    fix_epoch = [
        sentence(f"GPRMC,1200{s:02d}.00,A,3756.49000,N,02339.18000,E,0.1,,231126,,,A")
        + sentence(f"GPGGA,1200{s:02d}.00,3756.49000,N,02339.18000,E,1,08,1.0,42.0,M,34.0,M,,")
        for s in range(3)
    ]
    async with running(reader):
        await wait_until(lambda: reader.connected)
        for epoch in fix_epoch:
            await pty.write(epoch)
        await wait_until(lambda: len(seen.fixes) == 3)
        # The NEO-6M without a fix (hardware.md).
        for _ in range(2):
            await pty.write(b"$GPRMC,,V,,,,,,,,,,N*53\r\n$GPGGA,,,,,,0,00,99.99,,,,,,*48\r\n")
        await wait_until(lambda: len(seen.lost) == 1)
    assert seen.lost[0].reason == "receiver reports no fix"
    assert seen.lost[0].last_fix_time == seen.fixes[-1].time


def epoch(second: int) -> bytes:
    return sentence(
        f"GPRMC,1200{second:02d}.00,A,3756.49000,N,02339.18000,E,0.1,,231126,,,A"
    ) + sentence(f"GPGGA,1200{second:02d}.00,3756.49000,N,02339.18000,E,1,08,1.0,42.0,M,34.0,M,,")


async def test_vanished_port_is_retried_and_a_new_one_works(tmp_path: Path) -> None:
    bus = Bus()
    seen = Recorder(bus)
    first, second = Pty(), Pty()
    link = tmp_path / "gps"  # as udev's /dev/serial/by-id names follow a replugged adapter
    link.symlink_to(first.path)
    clock = ManualClock()
    reader = GpsReader(bus, GpsSection(port=str(link), fix_timeout=30.0), clock=clock)
    try:
        async with running(reader):
            await wait_until(lambda: reader.connected)
            await first.write(epoch(0))
            await wait_until(lambda: reader.decoder.sentences == 2)
            await advancing(clock, lambda: len(seen.fixes) == 1)
            # The USB adapter is pulled: its tty goes and udev removes the by-id link. (A link
            # left to the closed /dev/pts/N was opened again when another test's new pty took
            # that number, on a busy machine: reconnected to someone else's device.)
            first.close()
            link.unlink()
            await wait_until(lambda: not reader.connected)
            await wait_until(lambda: len(seen.lost) == 1)
            assert str(link) in seen.lost[0].reason
            await advancing(clock, lambda: bool(seen.stats) and not seen.stats[-1].connected)
            assert seen.stats[-1].error
            gone_at = clock.time()
            await advancing(clock, lambda: clock.time() > gone_at + 5)  # reopen attempts fail
            assert not reader.connected
            link.symlink_to(second.path)  # plugged in again, as another tty
            await advancing(clock, lambda: reader.connected)
            await second.write(epoch(1))
            await wait_until(lambda: reader.decoder.sentences == 2)  # the decoder starts over
            await advancing(clock, lambda: len(seen.fixes) == 2)
    finally:
        first.close()
        second.close()


async def test_silent_receiver_loses_the_fix(pty: Pty) -> None:
    bus = Bus()
    seen = Recorder(bus)
    clock = ManualClock()
    reader = GpsReader(bus, GpsSection(port=pty.path, fix_timeout=0.5), clock=clock)
    async with running(reader):
        await wait_until(lambda: reader.connected)
        await pty.write(epoch(0))
        await wait_until(lambda: reader.decoder.sentences == 2)
        await advancing(clock, lambda: len(seen.fixes) == 1)
        fixed_at = clock.time()
        await advancing(clock, lambda: len(seen.lost) == 1)  # the antenna cable is cut
        assert seen.lost[0].reason == "no fix for 0.5 s"
        assert 0.5 <= clock.time() - fixed_at <= 0.6
        await pty.write(epoch(5))
        await wait_until(lambda: reader.decoder.sentences == 4)
        await advancing(clock, lambda: len(seen.fixes) == 2)
    assert len(seen.lost) == 1


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=200) | st.sampled_from(receiver_lines("ublox-8")[:30])))
def test_decoder_survives_any_bytes(chunks: list[bytes]) -> None:
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    for chunk in chunks:
        for parsed in decoder.feed(chunk):
            assembler.feed(parsed, 0.0)
    assembler.poll(1.0)
    assert decoder.sentences >= 0
    assert all(count >= 0 for count in decoder.dropped.values())


_FIELD = st.text(alphabet="0123456789.,-+NSEWAVMKTxyz ", max_size=14)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["GPRMC", "GNGGA", "GPGLL", "GPVTG", "GNGSA", "GNZDA"]),
            st.lists(_FIELD, max_size=14),
        ),
        max_size=20,
    )
)
def test_valid_checksums_with_garbage_fields_never_raise(
    bodies: list[tuple[str, list[str]]],
) -> None:
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    for address, fields in bodies:
        for parsed in decoder.feed(sentence(",".join([address, *fields]))):
            for fix in assembler.feed(parsed, 0.0):
                assert fix is None or -90 <= fix.latitude <= 90
    assembler.poll(1.0)


async def test_a_second_reader_cannot_share_the_port(pty: Pty) -> None:
    first, second = (
        GpsReader(Bus(), GpsSection(port=pty.path)),
        GpsReader(Bus(), GpsSection(port=pty.path)),
    )
    async with running(first):
        await wait_until(lambda: first.connected)
        async with running(second):
            await wait_until(lambda: second.error != "")
            assert not second.connected
            assert "lock" in second.error


def test_fix_is_published_once_rmc_and_gga_arrive_not_at_the_end_of_the_cycle() -> None:
    """A NEO-6M-style cycle ends with GSV and GLL (~0.3 s of line at 9600 baud after GGA):
    once the reader has seen a full cycle, it publishes as soon as RMC and GGA are in."""
    log = NMEA / "ublox-lea-5h.log"
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    triggers: list[str] = []
    now = 0.0
    for raw in log.read_bytes().splitlines():
        if not raw.startswith(b"$"):
            continue
        now += 0.01
        for msg in decoder.feed(raw + b"\r\n"):
            fixes = [fix for fix in assembler.feed(msg, now) if fix is not None]
            triggers.extend(msg.sentence_type for _ in fixes)
    assert len(triggers) > 10
    # Only the first fix, and the first after the fix came back, wait for the learned end of
    # the cycle (GLL); every other goes out on GGA, right after RMC.
    assert triggers.count("GGA") >= len(triggers) - 3


async def test_a_hung_port_open_is_reported_and_never_stalls_the_loop(
    pty: Pty, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A USB adapter whose driver does not answer: the open blocks in the kernel. The loop
    keeps running, the hang is reported, and the port is read once the open returns."""
    release, calls = hang_serial_opens(monkeypatch)
    gaps: list[float] = []

    bus = Bus()
    seen = Recorder(bus)
    reader = GpsReader(bus, GpsSection(port=pty.path))
    reader.opener.timeout = 0.2  # reported as hung after 0.2 s instead of 5
    async with running(reader), asyncio.TaskGroup() as group:
        ticking = group.create_task(record_loop_gaps(gaps))
        await wait_until(lambda: "hangs" in reader.error)
        await wait_until(lambda: len(gaps) > 50)  # more attempts time out meanwhile
        assert len(calls) == 1  # a hung attempt is awaited again, not doubled
        assert not reader.connected
        release.set()
        await wait_until(lambda: reader.connected)
        await pty.write(epoch(0) + epoch(1))
        await wait_until(lambda: len(seen.fixes) >= 1)
        ticking.cancel()
    assert max(gaps) < 1.0, max(gaps)
