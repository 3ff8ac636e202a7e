"""MCAP files written on a thread of their own, behind a bounded queue (issue 23).

:meth:`Recorder.submit` may be called from any thread (the event loop, GStreamer's streaming
threads) and never blocks: a full queue drops the message and counts it. The writer thread
encodes each message, writes it into the current file's chunk, closes the chunk (zstd) and
syncs the file at least every ``chunk_seconds`` (a power cut loses about that much), starts a
new file every ``rotate_seconds`` (at a keyframe of the video channel, so every file starts
with one), and keeps the directory under its quota: oldest files deleted first by size, age and
the disk's free-space floor. A disk that cannot take more (the floor reached with nothing old
left to delete, or a write error) stops recording with a warning; it resumes by itself when
there is room again. Nothing here ever waits on the control path.

A file being written is ``NAME.mcap.active``; finished, it is renamed ``NAME.mcap``. A file
left ``.active`` by a crash is recovered at the next start: every chunk that was closed is
copied into a proper ``NAME.mcap``, the rest is lost.
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
import queue
import re
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from brasidas.recording import NAME_PATTERN
from brasidas.recording.schemas import MESSAGE_ENCODING, SCHEMA_ENCODING, ChannelSpec

_LOGGER = logging.getLogger(__name__)

SUFFIX = ".mcap"
ACTIVE_SUFFIX = ".mcap.active"
QUOTA_CHECK_S = 5.0
"""How often the writer re-checks the quota and free space while recording (and while stopped)."""
RESUME_FREE_BYTES = 16 * 1024**2
"""After a failed write, recording resumes only with this much free beyond the floor."""
BATCH_S = 0.05
"""The writer thread writes what was queued this often (a chunk closes every second)."""
VIDEO_GAP_S = 2.0
"""A rotation waits for a keyframe only while video came in the last this many seconds."""

Encode = Callable[[Any], bytes]
EventHandler = Callable[[int, str], None]
"""``(level, text)``: a warning or a state change of the recorder, from the writer thread."""


@dataclass(frozen=True)
class Quota:
    max_bytes: int
    keep_days: float
    min_free_bytes: int


@dataclass
class RecorderStats:
    """Counters, written by the writer thread (and ``submit``), read by anyone."""

    written: int = 0
    dropped: int = 0
    """Queue full: the writer could not keep up."""
    not_recording: int = 0
    """Messages refused while recording was stopped (disk full or failing)."""
    waiting_keyframe: int = 0
    """Video frames skipped until a keyframe (the start of every file)."""
    encode_errors: int = 0
    files: int = 0
    deleted: int = 0
    recovered: int = 0
    bytes_written: int = 0
    recording: bool = False
    reason: str = ""
    """Why it is not recording (disk full, write error), empty while it records."""
    current: str = ""

    def counters(self) -> dict[str, int]:
        return {
            "written": self.written,
            "dropped": self.dropped,
            "not_recording": self.not_recording,
            "waiting_keyframe": self.waiting_keyframe,
            "encode_errors": self.encode_errors,
            "files": self.files,
            "deleted": self.deleted,
            "recovered": self.recovered,
        }


@dataclass
class _Item:
    channel: int
    time_ns: int
    payload: Any
    encode: Encode | None = None
    keyframe: bool | None = None
    """Video only: whether this access unit is a keyframe (None: not video)."""


_STOP = object()


@dataclass
class _OpenFile:
    path: Path
    stream: BinaryIO
    writer: Writer
    channel_ids: dict[int, int] = field(default_factory=dict)
    started: float = 0.0
    last_chunk: float = 0.0
    pending: int = 0
    """Messages since the last closed chunk."""


class Recorder:
    """The recording directory's writer: ``start()``, ``submit(...)`` from anywhere, ``stop()``."""

    def __init__(
        self,
        directory: Path,
        channels: Sequence[ChannelSpec],
        *,
        prefix: str,
        quota: Quota,
        rotate_seconds: float = 600.0,
        chunk_seconds: float = 1.0,
        queue_messages: int = 2000,
        check_seconds: float = QUOTA_CHECK_S,
        video_channel: int | None = None,
        on_event: EventHandler | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.directory = directory
        self.channels = list(channels)
        self.prefix = re.sub(r"[^A-Za-z0-9_-]", "_", prefix) or "brasidas"
        self.quota = quota
        self.rotate_seconds = rotate_seconds
        self.chunk_seconds = chunk_seconds
        self.check_seconds = check_seconds
        self.video_channel = video_channel
        self.on_event = on_event
        self.clock = clock
        self.stats = RecorderStats()
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_messages)
        self._thread: threading.Thread | None = None
        self._file: _OpenFile | None = None
        self._stopped_for = ""
        self._write_failed = False
        self._next_check = 0.0
        self._last_video = -1e9
        self._rotate_due = False

    # ------------------------------------------------------------------ any thread

    def submit(
        self,
        channel: int,
        time_ns: int,
        payload: Any,
        encode: Encode | None = None,
        *,
        keyframe: bool | None = None,
    ) -> bool:
        """Queue one message (``payload`` bytes, or encoded by ``encode`` on the writer
        thread); False when it was dropped. Never blocks."""
        if self._thread is None or self._stopped_for:
            self.stats.not_recording += 1
            return False
        try:
            self._queue.put_nowait(_Item(channel, time_ns, payload, encode, keyframe))
        except queue.Full:
            self.stats.dropped += 1
            return False
        return True

    @property
    def queued(self) -> int:
        return self._queue.qsize()

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the writer thread (it recovers files a crash left first)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 0.5) -> None:
        """Finish the current file and end the thread (blocking: call it off the loop)."""
        thread = self._thread
        if thread is None:
            return
        while True:
            try:
                self._queue.put(_STOP, timeout=0.05)
                break
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self._queue.get_nowait()  # make room: shutting down beats a late message
                    self.stats.dropped += 1
        thread.join(timeout)
        if thread.is_alive():
            _LOGGER.warning("recorder: the writer thread did not finish in %.1f s", timeout)

    # ------------------------------------------------------------------ writer thread

    def _run(self) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            for leftover in sorted(self.directory.glob(f"*{ACTIVE_SUFFIX}")):
                self._recover(leftover)
        except OSError as err:
            self._stop_recording(f"cannot use {self.directory}: {err}")
        try:
            self._loop()
        finally:
            self._close_file()

    def _loop(self) -> None:
        """Wake every :data:`BATCH_S` and write what came meanwhile. Not woken by each message:
        a writer that ran the moment a message was queued would take the GIL exactly when the
        event loop is busy (a velocity datagram's way to the motors, say); in batches, it meets
        the loop only by chance, and gives the GIL back after every message."""
        while True:
            now = self.clock()
            time.sleep(min(BATCH_S, max(0.0, self._next_deadline(now) - now)))
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is _STOP:
                    return
                now = self.clock()
                if not self._stopped_for:
                    self._write(item, now)
                time.sleep(0)  # the GIL to the event loop's thread, if it waits
            now = self.clock()
            if now >= self._next_check:
                self._next_check = now + self.check_seconds
                self._check_space()
            self._maybe_close_chunk(now)

    def _next_deadline(self, now: float) -> float:
        deadline = self._next_check
        f = self._file
        if f is not None and f.pending:
            deadline = min(deadline, f.last_chunk + self.chunk_seconds)
        return deadline

    def _write(self, item: _Item, now: float) -> None:
        is_video = item.keyframe is not None
        if is_video:
            self._last_video = now
        f = self._file
        if f is not None and now - f.started >= self.rotate_seconds:
            video_recent = now - self._last_video < VIDEO_GAP_S
            if not video_recent or (is_video and item.keyframe):
                self._close_file()
                f = None
                self._check_space()  # the finished file may put the directory past its quota
                if self._stopped_for:
                    return
        if f is None:
            if is_video and not item.keyframe:
                self.stats.waiting_keyframe += 1
                return
            f = self._open_file(now)
            if f is None:
                return
        if is_video and item.channel not in f.channel_ids and not item.keyframe:
            self.stats.waiting_keyframe += 1
            return
        try:
            data = item.encode(item.payload) if item.encode is not None else item.payload
        except Exception:
            self.stats.encode_errors += 1
            _LOGGER.exception("recorder: a message on channel %d did not encode", item.channel)
            return
        try:
            channel_id = f.channel_ids.get(item.channel)
            if channel_id is None:
                channel_id = self._register(f, item.channel)
            f.writer.add_message(channel_id, item.time_ns, data, item.time_ns)
        except OSError as err:
            self._stop_recording(f"write failed: {err}", write_failed=True)
            return
        f.pending += 1
        self.stats.written += 1

    def _register(self, f: _OpenFile, index: int) -> int:
        """Channels are added to a file when their first message arrives, so a file lists only
        what it holds."""
        spec = self.channels[index]
        schema_id = f.writer.register_schema(spec.schema_name, SCHEMA_ENCODING, spec.schema_bytes())
        channel_id = f.writer.register_channel(spec.topic, MESSAGE_ENCODING, schema_id)
        f.channel_ids[index] = channel_id
        return channel_id

    def _maybe_close_chunk(self, now: float) -> None:
        f = self._file
        if f is None or not f.pending or now - f.last_chunk < self.chunk_seconds:
            return
        try:
            f.writer.flush()  # type: ignore[no-untyped-call]
            os.fsync(f.stream.fileno())
        except OSError as err:
            self._stop_recording(f"write failed: {err}", write_failed=True)
            return
        f.pending = 0
        f.last_chunk = now
        self.stats.bytes_written = f.stream.tell()

    def _open_file(self, now: float) -> _OpenFile | None:
        stamp = datetime.datetime.fromtimestamp(now, datetime.UTC).strftime("%Y%m%dT%H%M%S")
        millis = int(now * 1000) % 1000
        name = f"{stamp}.{millis:03d}Z-{self.prefix}"
        path = self.directory / f"{name}{ACTIVE_SUFFIX}"
        try:
            stream: BinaryIO = open(path, "wb")  # closed by _close_file
            writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=4 * 1024 * 1024)
            writer.start(profile="", library="brasidas")
            stream.flush()  # the magic and header on disk at once: a listed file is an MCAP
        except OSError as err:
            self._stop_recording(f"cannot create {path.name}: {err}")
            return None
        self._file = _OpenFile(path, stream, writer, started=now, last_chunk=now)
        self.stats.files += 1
        self.stats.current = path.name
        self.stats.recording = True
        return self._file

    def _close_file(self) -> None:
        """Finish the file (its summary) and name it ``.mcap``; a file that cannot be finished
        (the disk failed) keeps its ``.active`` name, for the next start to recover."""
        f = self._file
        if f is None:
            return
        self._file = None
        self.stats.current = ""
        finished = False
        try:
            f.writer.finish()  # type: ignore[no-untyped-call]
            f.stream.flush()
            os.fsync(f.stream.fileno())
            finished = True
        except OSError as err:
            _LOGGER.warning("recorder: finishing %s failed: %s", f.path.name, err)
        finally:
            with contextlib.suppress(OSError):  # what the buffer still held cannot be written
                f.stream.close()
        if finished:
            with contextlib.suppress(OSError):
                f.path.rename(f.path.with_name(f.path.name.removesuffix(ACTIVE_SUFFIX) + SUFFIX))

    def _stop_recording(self, reason: str, *, write_failed: bool = False) -> None:
        if self._stopped_for:
            return
        # Said before it shows in the stats: whoever sees the reason finds the warning logged.
        _LOGGER.warning("recorder stopped: %s", reason)
        self._stopped_for = reason
        self._write_failed = write_failed
        self.stats.recording = False
        self.stats.reason = reason
        self._close_file()
        self._event(3, f"recording stopped: {reason}")

    def _resume(self) -> None:
        _LOGGER.info("recorder: room again, recording resumes")
        self._stopped_for = ""
        self.stats.reason = ""
        self._event(2, "recording resumed")

    def _event(self, level: int, text: str) -> None:
        if self.on_event is not None:
            try:
                self.on_event(level, text)
            except Exception:
                _LOGGER.exception("recorder: event handler failed")

    # ------------------------------------------------------------------ quota

    def _check_space(self) -> None:
        """Delete the oldest finished files past the quota; stop when even that is not enough."""
        try:
            reason = enforce_quota(self.directory, self.quota, self.clock(), self._deleted)
        except OSError as err:
            reason = f"cannot check {self.directory}: {err}"
        if reason and not self._stopped_for:
            self._stop_recording(reason)
        elif not reason and self._stopped_for:
            if self._write_failed:
                # The disk refused a write (full below the floor, or failing): wait for room
                # beyond the floor, or it would stop again at once, a file at a time.
                try:
                    free = shutil.disk_usage(self.directory).free
                except OSError:
                    return
                if free < self.quota.min_free_bytes + RESUME_FREE_BYTES:
                    return
            self._resume()

    def _deleted(self, path: Path) -> None:
        self.stats.deleted += 1
        _LOGGER.info("recorder: deleted %s (quota)", path.name)

    # ------------------------------------------------------------------ recovery

    def _recover(self, path: Path) -> None:
        """Copy every complete record of a crashed file into a finished one; drop the rest."""
        target = path.with_name(path.name.removesuffix(ACTIVE_SUFFIX) + SUFFIX)
        count = recover_file(path, target)
        path.unlink(missing_ok=True)
        if count:
            self.stats.recovered += 1
            _LOGGER.warning("recorder: recovered %s (%d messages)", target.name, count)
        else:
            target.unlink(missing_ok=True)
            _LOGGER.warning("recorder: %s held no complete chunk; removed", path.name)


def enforce_quota(
    directory: Path, quota: Quota, now: float, on_delete: Callable[[Path], None]
) -> str:
    """Delete finished recordings, oldest first, past ``quota``; the reason recording cannot
    go on (empty: it can)."""
    finished = sorted(directory.glob(f"*{SUFFIX}"))
    active = [(p, p.stat().st_size) for p in directory.glob(f"*{ACTIVE_SUFFIX}")]
    sizes = {p: p.stat().st_size for p in finished}
    total = sum(sizes.values()) + sum(size for _p, size in active)
    oldest_kept = now - quota.keep_days * 86400
    for path in finished:
        free = shutil.disk_usage(directory).free
        too_old = path.stat().st_mtime < oldest_kept
        if not too_old and total <= quota.max_bytes and free >= quota.min_free_bytes:
            break
        path.unlink(missing_ok=True)
        total -= sizes[path]
        on_delete(path)
    free = shutil.disk_usage(directory).free
    if free < quota.min_free_bytes:
        return f"disk full: {free // 1024**2} MiB free, below the floor of {quota.min_free_bytes // 1024**2} MiB"
    if total > quota.max_bytes:
        return f"quota reached: {total // 1024} KiB recorded, limit {quota.max_bytes // 1024} KiB"
    return ""


def recover_file(source: Path, target: Path) -> int:
    """Copy the schemas, channels and messages of every complete record of ``source`` (an MCAP
    file cut short) into a new, finished ``target``; returns the messages copied."""
    count = 0
    with open(source, "rb") as stream, open(target, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="", library="brasidas (recovered)")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        try:
            for record in StreamReader(stream, skip_magic=False).records:
                if isinstance(record, Schema):
                    schemas[record.id] = writer.register_schema(
                        record.name, record.encoding, record.data
                    )
                elif isinstance(record, Channel) and record.schema_id in schemas:
                    channels[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schemas[record.schema_id]
                    )
                elif isinstance(record, Message) and record.channel_id in channels:
                    writer.add_message(
                        channels[record.channel_id],
                        record.log_time,
                        record.data,
                        record.publish_time,
                    )
                    count += 1
        except Exception as err:  # the cut: a truncated record, a bad CRC, end of file
            _LOGGER.info("recorder: %s ends at a cut record (%s)", source.name, err)
        writer.finish()  # type: ignore[no-untyped-call]
    return count


def summary_channels(summary: Any) -> dict[str, dict[str, Any]]:
    """An MCAP summary's channels by topic: each one's schema name and message count (the
    recordings listing and the replay index both show them)."""
    stats = summary.statistics
    return {
        channel.topic: {
            "schema": summary.schemas[channel.schema_id].name
            if channel.schema_id in summary.schemas
            else "",
            "messages": stats.channel_message_counts.get(channel_id, 0) if stats else 0,
        }
        for channel_id, channel in summary.channels.items()
    }


def list_recordings(directory: Path) -> list[dict[str, Any]]:
    """Every recording in ``directory``: name, start, duration, size, channels and counts
    (finished files from their summary; the one being written by its name and size)."""
    from mcap.reader import make_reader

    items: list[dict[str, Any]] = []
    if not directory.is_dir():
        return items
    for path in sorted(directory.iterdir()):
        name = path.name
        if not (name.endswith(SUFFIX) or name.endswith(ACTIVE_SUFFIX)):
            continue
        try:
            size = path.stat().st_size
        except OSError:
            continue
        entry: dict[str, Any] = {
            "name": name,
            "size": size,
            "recording": name.endswith(ACTIVE_SUFFIX),
            "start": None,
            "duration_s": None,
            "messages": None,
            "channels": {},
        }
        if not entry["recording"]:
            try:
                with open(path, "rb") as stream:
                    summary = make_reader(stream).get_summary()
            except Exception as err:
                entry["error"] = f"unreadable: {err}"
                summary = None
            if summary is not None and summary.statistics is not None:
                stats = summary.statistics
                entry["start"] = stats.message_start_time / 1e9
                entry["duration_s"] = round(
                    (stats.message_end_time - stats.message_start_time) / 1e9, 3
                )
                entry["messages"] = stats.message_count
                entry["channels"] = summary_channels(summary)
        items.append(entry)
    return items


def resolve_name(directory: Path, name: str) -> Path | None:
    """The file of recording ``name`` (finished or being written), or None: never a path
    outside ``directory``."""
    base = name.removesuffix(".active")
    if not NAME_PATTERN.match(base):
        return None
    path = directory / name
    # Not a symbolic link: one planted in the folder would serve whatever it points at.
    return path if path.is_file() and not path.is_symlink() else None
