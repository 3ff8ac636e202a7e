"""The pipeline base class (the seed's PiGstPLBase): start, pause, stop, state.

A :class:`PipelineStream` owns one ``Gst.Pipeline`` built by :meth:`PipelineStream.build`.
Its public methods must be called on the event loop. GStreamer bus messages arrive on
GStreamer's threads and reach the loop only through ``loop.call_soon_threadsafe`` (a bus sync
handler, so no GLib main loop is needed; the loop then empties the bus queue). State changes
that may block (opening a device, joining streaming threads) run in the default executor.

An error (missing element or device, caps that do not negotiate, a source that vanishes)
sets ``failed`` with a readable reason. The owner runs :meth:`PipelineStream.supervise` in
its task group: it tears the failed pipeline down and rebuilds it with capped backoff while
the stream is still wanted. Each stream fails and recovers on its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import weakref
from collections.abc import Callable
from enum import StrEnum
from typing import Any

from brasidas.backoff import Backoff
from brasidas.media.gst import MediaError, gst, gst_off_the_loop, realtime_clock
from brasidas.threads import in_daemon_thread

_LOGGER = logging.getLogger(__name__)

SLOW_STATE_CHANGE_S = 1.0
"""A state change slower than this is logged: a device or the network is holding it up."""


class StreamState(StrEnum):
    IDLE = "idle"
    PLAYING = "playing"
    PAUSED = "paused"
    FAILED = "failed"


class PipelineStream:
    """One GStreamer pipeline with a small state machine; subclasses implement ``build``."""

    kind = "stream"

    def __init__(
        self,
        name: str,
        *,
        on_change: Callable[[PipelineStream], None] | None = None,
        retry_initial: float = 1.0,
        retry_max: float = 30.0,
        healthy_after: float = 10.0,
        state_change_timeout: float = 5.0,
    ) -> None:
        self.name = name
        self.on_change = on_change
        """Called on the loop after every state change (publish it, update telemetry)."""
        self.retry_initial = retry_initial
        self.retry_max = retry_max
        self.healthy_after = healthy_after
        self.state_change_timeout = state_change_timeout
        self.state = StreamState.IDLE
        self.reason = ""
        self.failures = 0
        self.retries = 0
        self.abandoned = 0
        """Pipelines given up on because a state change never returned (a GStreamer deadlock)."""
        self.next_retry_in: float | None = None
        self.retry = True
        """Rebuild the pipeline after a failure (command 10.10 switches it for every stream)."""
        self.pipeline: Any = None
        self._wanted = StreamState.IDLE
        self._generation = 0
        self._playing_since: float | None = None
        self._last_error = ""
        self._last_error_detail = ""
        self._attempt_failed = False
        self._drain_pending = False
        self._lock = asyncio.Lock()
        self._failed = asyncio.Event()
        self._kick = asyncio.Event()

    # ------------------------------------------------------------------ subclass API

    def build(self) -> Any:
        """A new, linked ``Gst.Pipeline`` (not started); raise MediaError with the reason."""
        raise NotImplementedError

    def destination(self) -> str:
        """Where the stream goes or listens ("host:port"), for status messages."""
        return ""

    def describe(self) -> dict[str, Any]:
        """Parameters for ``list_streams`` and ``connect`` (subclasses add theirs)."""
        return {
            "name": self.name,
            "kind": self.kind,
            "state": self.state.value,
            "reason": self.reason,
            "destination": self.destination() if self.state is not StreamState.IDLE else "",
            "failures": self.failures,
            "retries": self.retries,
            "abandoned": self.abandoned,
        }

    def on_built(self, pipeline: Any) -> None:
        """Hook after build, before the first state change (e.g. keep element references)."""

    def on_torn_down(self) -> None:
        """Hook after the pipeline went to NULL and was dropped."""

    # ------------------------------------------------------------------ control (event loop)

    @property
    def wanted(self) -> StreamState:
        return self._wanted

    async def start(self) -> StreamState:
        """Play (building the pipeline if needed); resumes a paused stream."""
        async with self._lock:
            self._wanted = StreamState.PLAYING
            self._kick.set()
            await self._go(StreamState.PLAYING)
            return self.state

    async def pause(self) -> StreamState:
        """Pause a playing stream (resume with :meth:`start`); an idle one stays idle."""
        async with self._lock:
            if self.state is StreamState.IDLE or self._wanted is StreamState.IDLE:
                return self.state
            self._wanted = StreamState.PAUSED
            self._kick.set()
            if self.state is StreamState.FAILED:
                return self.state
            await self._go(StreamState.PAUSED)
            return self.state

    async def stop(self) -> StreamState:
        """Stop and release the pipeline; idempotent."""
        async with self._lock:
            self._wanted = StreamState.IDLE
            self._kick.set()
            await self._teardown()
            self.reason = ""
            self._set_state(StreamState.IDLE)
            return self.state

    async def restart(self) -> StreamState:
        """Rebuild the pipeline with the current parameters, keeping the wanted state."""
        async with self._lock:
            wanted = self._wanted
            await self._teardown()
            if wanted is not StreamState.IDLE:
                await self._go(wanted)
            return self.state

    def _stopped_on_purpose(self) -> bool:
        """Stopped by its owner: a failure then is not retried. (A method, not an inline test,
        because the answer can change across every await in :meth:`supervise`.)"""
        return self._wanted is StreamState.IDLE

    def set_retry(self, on: bool) -> None:
        """Retry failures or not (10.10); switched back on, a failed stream is retried."""
        self.retry = on
        if on and self.state is StreamState.FAILED:
            self._failed.set()

    async def supervise(self) -> None:
        """Run by the owner for the stream's lifetime: retry failures with capped backoff."""
        backoff = Backoff(self.retry_initial, max(self.retry_initial, self.retry_max))
        delay = backoff.next()
        while True:
            await self._failed.wait()
            self._failed.clear()
            async with self._lock:
                if self.state is not StreamState.FAILED:
                    continue
                if (
                    self._playing_since is not None
                    and time.monotonic() - self._playing_since > self.healthy_after
                ):
                    backoff.reset()
                    delay = backoff.next()
                self._playing_since = None
                await self._teardown()
            if self._stopped_on_purpose() or not self.retry:
                continue
            self.next_retry_in = delay
            self._kick.clear()
            with contextlib.suppress(TimeoutError):
                # A start/pause/stop in the meantime ends the wait early. (asyncio.timeout,
                # not wait_for: 3.11's wait_for can swallow a cancel that races the event.)
                async with asyncio.timeout(delay):
                    await self._kick.wait()
            self.next_retry_in = None
            async with self._lock:
                if self.state is not StreamState.FAILED or self._stopped_on_purpose():
                    continue
                self.retries += 1
                _LOGGER.info("stream %s: retrying after %.1f s", self.name, delay)
                delay = backoff.next()
                await self._go(self._wanted)

    # ------------------------------------------------------------------ internals (event loop)

    async def _go(self, target: StreamState) -> None:
        if self.pipeline is None:
            try:
                await gst_off_the_loop()  # a daemon's first stream: GStreamer initialised
                pipeline = self.build()
            except MediaError as err:
                self._attempt_failed = False
                self._fail(str(err))
                return
            self._attach(pipeline)
        self._last_error = self._last_error_detail = ""
        self._attempt_failed = False
        Gst = gst()
        gst_state = Gst.State.PLAYING if target is StreamState.PLAYING else Gst.State.PAUSED
        pipeline = self.pipeline
        generation = self._generation
        result = await self._change_state(pipeline, gst_state)
        if generation != self._generation:
            return  # torn down meanwhile
        if result == Gst.StateChangeReturn.FAILURE:
            reason = self._last_error or f"{self.name}: pipeline refused to start"
            self._fail(reason, self._last_error_detail)
            return
        if self._attempt_failed:
            return  # an error message beat us here
        if target is StreamState.PLAYING and self._playing_since is None:
            self._playing_since = time.monotonic()
        self.reason = ""
        self._set_state(target)

    async def _change_state(self, pipeline: Any, state: Any) -> Any:
        """``set_state`` in a thread of its own (it can block on devices and the network, and
        GStreamer 1.22's rtpjitterbuffer can deadlock against its own task while deactivating):
        a change that has not returned after ``state_change_timeout`` is given up as a
        failure, and the daemon thread it is stuck in does not keep the process from exiting.
        """
        started = time.monotonic()
        done = in_daemon_thread(f"gst-state:{self.name}", pipeline.set_state, state)
        try:
            async with asyncio.timeout(self.state_change_timeout):
                result = await asyncio.shield(done)
        except TimeoutError:
            _LOGGER.error(
                "stream %s: GStreamer did not reach %s in %.0f s; pipeline abandoned",
                self.name,
                state.value_nick,
                self.state_change_timeout,
            )
            self.abandoned += 1
            return gst().StateChangeReturn.FAILURE
        took = time.monotonic() - started
        if took > SLOW_STATE_CHANGE_S:
            _LOGGER.warning("stream %s: %s took %.1f s", self.name, state.value_nick, took)
        return result

    def _attach(self, pipeline: Any) -> None:
        self._generation += 1
        pipeline.use_clock(realtime_clock())
        bus = pipeline.get_bus()
        loop = asyncio.get_running_loop()
        bus.set_sync_handler(_sync_handler, (weakref.ref(self), loop, self._generation))
        # A source's end of stream is the stream's: the pipeline posts EOS only once every sink
        # has it, and a sink fed from elsewhere (rtpbin's RTCP, a tee's other branch) may never.
        Gst = gst()
        data = (weakref.ref(self), loop, self._generation)
        for source in _iterate(pipeline.iterate_sources()):
            for pad in source.srcpads:
                pad.add_probe(Gst.PadProbeType.EVENT_DOWNSTREAM, _source_eos_probe, data)
        self.pipeline = pipeline
        self.on_built(pipeline)

    async def _teardown(self) -> None:
        pipeline = self.pipeline
        if pipeline is None:
            return
        self.pipeline = None
        self._generation += 1  # late messages from the old pipeline are ignored
        abandoned = self.abandoned
        await self._change_state(pipeline, gst().State.NULL)
        if self.abandoned == abandoned:  # an abandoned one may hold locks get_bus() needs
            pipeline.get_bus().set_sync_handler(None)  # releases the handler's closure
        self._playing_since = None
        self.on_torn_down()

    def _fail(self, reason: str, detail: str = "") -> None:
        """``detail``: GStreamer's debug string (where it was raised), logged with the reason:
        what the next failure nobody can reproduce needs."""
        if self._attempt_failed:
            return  # the same attempt reported twice (bus error and set_state result)
        self._attempt_failed = True
        self.failures += 1
        self.reason = reason
        if detail:
            _LOGGER.warning("stream %s failed: %s [%s]", self.name, reason, detail)
        else:
            _LOGGER.warning("stream %s failed: %s", self.name, reason)
        self._set_state(StreamState.FAILED)
        self._failed.set()

    def _set_state(self, state: StreamState) -> None:
        changed = state is not self.state
        self.state = state
        if state is not StreamState.FAILED and changed:
            _LOGGER.info("stream %s %s", self.name, state.value)
        if self.on_change is not None:
            try:
                self.on_change(self)
            except Exception:
                _LOGGER.exception("stream %s: state listener failed", self.name)

    def _on_message(self, generation: int, kind: str, text: str, detail: str) -> None:
        """Bus message forwarded to the loop."""
        self._drain_pending = False
        if self.pipeline is not None:
            bus = self.pipeline.get_bus()
            while bus.pop() is not None:
                pass  # already seen by the sync handler
        if generation != self._generation or not kind:
            return
        if kind == "error":
            self._fail(self.explain(text), detail)
        elif kind == "eos":
            self._fail(f"{self.name}: end of stream (source stopped)")
        elif kind == "warning":
            _LOGGER.warning("stream %s: %s", self.name, text)
        else:
            self.on_element_message(kind, text)

    def explain(self, error: str) -> str:
        """The readable reason for a GStreamer error (subclasses add context)."""
        return error

    def on_element_message(self, kind: str, text: str) -> None:
        """Other forwarded messages (``kind`` is the structure name); override as needed."""


ERROR_CAUSE_MAX_CHARS = 160


def error_text(source: str, message: str, detail: str | None) -> str:
    """``source: message (cause)``, the cause being the last line of GStreamer's debug string:
    a source's "Internal data stream error" says why its streaming stopped only there
    ("streaming stopped, reason not-negotiated (-4)")."""
    lines = [line.strip() for line in (detail or "").splitlines() if line.strip()]
    cause = lines[-1][:ERROR_CAUSE_MAX_CHARS] if lines else ""
    if not cause or cause in message:
        return f"{source}: {message}"
    return f"{source}: {message} ({cause})"


def _iterate(iterator: Any) -> list[Any]:
    """The items of a GstIterator (bins are not changed while it is read)."""
    Gst = gst()
    items: list[Any] = []
    while True:
        result, item = iterator.next()
        if result == Gst.IteratorResult.OK:
            items.append(item)
        elif result == Gst.IteratorResult.RESYNC:
            iterator.resync()
            items.clear()
        else:
            return items


def _source_eos_probe(pad: Any, info: Any, data: tuple[Any, ...]) -> Any:
    """GStreamer thread: a source's EOS event, told to the loop as the bus's EOS would be."""
    Gst = gst()
    event = info.get_event()
    if event is not None and event.type == Gst.EventType.EOS:
        ref, loop, generation = data
        stream = ref()
        if stream is not None:
            with contextlib.suppress(RuntimeError):  # loop closed: nobody to tell
                loop.call_soon_threadsafe(stream._on_message, generation, "eos", "", "")
    return Gst.PadProbeReturn.OK


def _sync_handler(bus: Any, message: Any, data: tuple[Any, ...]) -> Any:
    """GStreamer thread: forward what matters to the loop; never touch stream state here."""
    ref, loop, generation = data
    Gst = gst()
    kind = ""
    text = detail = ""
    mtype = message.type
    if mtype == Gst.MessageType.ERROR:
        err, detail = message.parse_error()
        source = message.src.get_name() if message.src is not None else "pipeline"
        kind, text = "error", error_text(source, err.message, detail)
        stream = ref()
        if stream is not None:
            # Read by the executor thread's caller after set_state.
            stream._last_error, stream._last_error_detail = text, detail or ""
    elif mtype == Gst.MessageType.EOS:
        kind = "eos"
    elif mtype == Gst.MessageType.WARNING:
        warn, detail = message.parse_warning()
        kind, text = "warning", warn.message
    elif mtype == Gst.MessageType.ELEMENT:
        structure = message.get_structure()
        if structure is not None:
            kind, text = structure.get_name(), structure.to_string()
    stream = ref()
    if stream is not None and (kind or not stream._drain_pending):
        stream._drain_pending = True
        with contextlib.suppress(RuntimeError):  # loop closed: nobody to tell
            loop.call_soon_threadsafe(stream._on_message, generation, kind, text, detail or "")
    # PASS, and the loop pops the queue: with PyGObject, a message DROPped here is never
    # freed, and it holds its source element (and so the whole pipeline) alive.
    return Gst.BusSyncReply.PASS
