"""Arming, pre-arm checks, the stop every operator may send, the operator's last word (issue 27).

The platform is *disarmed* (the motion arbiter holds the motors at zero) or *armed*. Arming
runs the pre-arm checks and refuses with every failing reason. Moving needs control (``arm``,
a patrol start, engaging the override: each arms through the checks); stopping never does:
any authenticated station session and any trusted ground station may ``stop`` or ``disarm``,
and who did is kept. The operator's last word (start, stop, hold, disarm) is written to
``arming.state_file`` before the answer, so it is obeyed after any restart, clean or not:
after a stop nothing moves until an operator says so; after a start, ``autonomy.autostart``
resumes the patrol through the pre-arm checks and an announced countdown.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.route import RouteError, write_atomically
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.codecs.telemetry_schema import Arming, RecorderStatus
from brasidas.messages import (
    ArmingState,
    CommandReceived,
    ControllerStatus,
    ControlState,
    GpsFix,
    GpsFixLost,
    ImuStatus,
    OverrideState,
    SafetyNotice,
    SessionClosed,
)
from brasidas.security import state_dir
from platformd.context import PlatformContext
from platformd.session_table import Session

_LOGGER = logging.getLogger(__name__)

CLOCK_SET_AFTER = 1_704_067_200.0
"""2024-01-01 UTC: a wall clock before it was never set (a Pi without RTC before NTP)."""
IMU_SILENT_S = 3.0
"""No IMU status for this long: ``PreArm: IMU silent`` (the driver reports about 1 Hz)."""
TICK_S = 0.1
"""How often the countdown and the autostart's pre-arm checks are looked at."""
NOTICE_WARNING = 4
NOTICE_NOTICE = 5
NOTICE_CRITICAL = 2
"""MAVLink severities (MAV_SEVERITY_*) of the announcements."""

STOP_WORDS = ("stop", "hold", "disarm", "terminate")
"""Last words after which nothing moves until an operator says so."""


@dataclass(frozen=True)
class LastWord:
    """What an operator said last, who, and when (wall clock, seconds)."""

    word: str
    by: str
    at: float


class LastWordStore:
    """The last word in one small JSON file, replaced atomically (a crash leaves the old or
    the new one). Blocking: call from a worker thread."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def load(self) -> LastWord | None:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            return LastWord(str(data["word"]), str(data.get("by", "")), float(data.get("at", 0)))
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            # Unreadable: the safe reading is "stopped" (an operator starts it again).
            _LOGGER.error("arming: %s unreadable (%s): treated as a stop", self.path, exc)
            return LastWord("stop", f"unreadable {self.path.name}", 0.0)

    def save(self, word: LastWord) -> None:
        write_atomically(self.path, json.dumps(asdict(word)))


@dataclass(frozen=True)
class PrearmInputs:
    """What the pre-arm checks look at, gathered from the bus (sans-IO: tests build one)."""

    now: float
    wall: float
    gps_enabled: bool = False
    fix_age_s: float | None = None
    fix_stale_s: float = 2.0
    imu_enabled: bool = False
    imu: ImuStatus | None = None
    imu_age_s: float | None = None
    up_s: float = 0.0
    """Since the platform started."""
    motor_enabled: bool = False
    controller: ControllerStatus | None = None
    recorder_error: str = ""
    map_error: str = ""
    check_clock: bool = True


def prearm_reasons(inputs: PrearmInputs, *, manual: bool = False) -> tuple[str, ...]:
    """Every failing pre-arm check, as ``PreArm: ...``; empty when arming may proceed.

    ``manual``: engaging the override, the controller taking the robot by hand: nothing
    here is needed to drive by hand (teleop carries on with a full disk, issue 23; a
    controller that does not answer moves nothing either), so nothing refuses."""
    if manual:
        return ()
    reasons: list[str] = []
    if inputs.gps_enabled:
        if inputs.fix_age_s is None or inputs.fix_age_s > inputs.fix_stale_s:
            reasons.append("PreArm: no GPS fix")
    if inputs.imu_enabled:
        imu = inputs.imu
        if imu is not None and imu.error:
            reasons.append(f"PreArm: IMU: {imu.error}")
        elif inputs.up_s > IMU_SILENT_S and (
            imu is None or not imu.ok or inputs.imu_age_s is None or inputs.imu_age_s > IMU_SILENT_S
        ):  # a driver still starting (no sample yet, no error) is not silent yet
            reasons.append("PreArm: IMU silent")
    if inputs.motor_enabled:
        controller = inputs.controller
        if controller is None or not controller.connected:
            why = controller.error if controller is not None and controller.error else ""
            reasons.append("PreArm: motor controller not answering" + (f" ({why})" if why else ""))
    if inputs.map_error:
        reasons.append(f"PreArm: map refused: {inputs.map_error}")
    if inputs.recorder_error:
        reasons.append(f"PreArm: recorder cannot write: {inputs.recorder_error}")
    if inputs.check_clock and inputs.wall < CLOCK_SET_AFTER:
        reasons.append("PreArm: clock not set")
    return tuple(reasons)


def who(session: Session | None) -> str:
    """How a stop's sender is named: its station id (``gcs255@HOST:PORT`` for MAVLink)."""
    return session.station_id if session is not None else "the platform"


class ArmingActor(Actor):
    """Armed or not; the checks, the stop, the countdown and the last word on disk."""

    name = "arming"

    def __init__(
        self,
        ctx: PlatformContext,
        store: LastWordStore,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.store = store
        self._clock = clock
        self._wall = wall
        self.armed = False
        self.last_word: LastWord | None = None
        self.last_stop = ""
        self.countdown_until: float | None = None
        self.autostart_pending = False
        self.counters: dict[str, int] = dict.fromkeys(
            ("arms", "arm_refused", "disarms", "stops", "autostarts"), 0
        )
        self._started = clock()
        self._fix_at: float | None = None
        self._imu_at: float | None = None
        self._announced: tuple[str, ...] = ()
        self._saving = asyncio.Lock()
        self._said = asyncio.Event()
        """A word said by a synchronous hook waits to be written."""
        self._unsaved = False
        self._controller_session: str | None = None

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Read the last word, publish disarmed, hook the patrol (before the daemon is up)."""
        self.last_word = await asyncio.to_thread(self.store.load)
        word = self.last_word
        if word is not None and word.word in STOP_WORDS:
            self.last_stop = _stop_text(word)
        self._publish("disarmed at start")
        patrol = self.ctx.patrol
        if patrol is not None:
            patrol.start_check = self._before_patrol_start
            patrol.on_stop = self._on_patrol_stop
            patrol.settle = self.flush
            # Only after a start: a route uploaded (or set) and never started stays put.
            resumes = word is not None and word.word == "start"
            if self.ctx.config.autonomy.autostart and patrol.resumable and resumes:
                self.autostart_pending = True
                _LOGGER.warning("arming: autostart: the patrol resumes after pre-arm checks")
            elif patrol.resumable and word is not None and word.word in STOP_WORDS:
                _LOGGER.warning(
                    "arming: not resuming the patrol: the last word was %s", _stop_text(word)
                )

    async def run(self) -> None:
        self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.GPS_FIX_LOST, self._on_fix_lost)
        self.subscribe(topics.IMU_STATUS, self._on_imu)
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.subscribe(topics.CONTROL_STATE, self._on_control)
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        async with asyncio.TaskGroup() as group:
            group.create_task(self._write_forever(), name="arming:last-word")
            while True:
                await self.tick()
                await asyncio.sleep(TICK_S)

    async def flush(self) -> None:
        """Until the last word said is on disk."""
        if self._unsaved and self.last_word is not None:
            self._unsaved = False
            await self.remember(self.last_word)
        else:
            async with self._saving:
                pass  # a write in flight has finished

    async def _write_forever(self) -> None:
        """Writes a word said from a synchronous hook (a patrol start or stop) at once."""
        while True:
            await self._said.wait()
            self._said.clear()
            if self._unsaved and self.last_word is not None:
                self._unsaved = False
                await self.remember(self.last_word)

    async def async_stop(self) -> None:
        if self._unsaved and self.last_word is not None:  # said just before the stop
            self._unsaved = False
            await self.remember(self.last_word)
        if self.armed:
            self.armed = False
            self._publish("platform stopping")

    # ------------------------------------------------------------------ checks

    def inputs(self) -> PrearmInputs:
        config = self.ctx.config
        now = self._clock()
        recorder_error = ""
        if config.recorder.enabled and config.arming.check_recorder:
            if RecorderStatus in self.ctx.telemetry:
                status = self.ctx.telemetry.build_one(RecorderStatus)
                if isinstance(status, RecorderStatus) and not status.recording:
                    recorder_error = status.reason
        patrol = self.ctx.patrol
        imu_seen = self._imu_at
        return PrearmInputs(
            now=now,
            wall=self._wall(),
            gps_enabled=config.gps.enabled and config.arming.check_gps,
            fix_age_s=None if self._fix_at is None else now - self._fix_at,
            fix_stale_s=config.autonomy.fix_stale_s,
            imu_enabled=config.imu.enabled,
            imu=self.bus.last(topics.IMU_STATUS),
            imu_age_s=None if imu_seen is None else now - imu_seen,
            up_s=now - self._started,
            motor_enabled=config.motor.enabled,
            controller=self.bus.last(topics.CONTROLLER_STATUS),
            recorder_error=recorder_error,
            map_error=patrol.map_error if patrol is not None else "",
            check_clock=config.arming.check_clock,
        )

    def reasons(self, *, manual: bool = False) -> tuple[str, ...]:
        return prearm_reasons(self.inputs(), manual=manual)

    # ------------------------------------------------------------------ requests

    def arm(self, by: str, *, manual: bool = False) -> str | None:
        """Arm through the pre-arm checks: None, or every failing reason in one line."""
        if self.armed:
            return None
        reasons = self.reasons(manual=manual)
        if reasons:
            self.counters["arm_refused"] += 1
            text = "; ".join(reasons)
            self._notice(NOTICE_WARNING, f"arming refused: {text}")
            return text
        self.armed = True
        self.counters["arms"] += 1
        self._publish(f"armed by {by}")
        self._notice(NOTICE_NOTICE, f"armed by {by}")
        return None

    async def stop(self, session: Session | None, word: str, *, force: bool = False) -> None:
        """Stop, hold or disarm for anyone: motors to zero, the patrol stopped, the
        countdown cancelled, the word (and who) on disk before this returns."""
        by = who(session)
        self.autostart_pending = False
        self.countdown_until = None
        was_armed = self.armed
        self.armed = False
        self._publish(f"{word} by {by}")
        patrol = self.ctx.patrol
        if patrol is not None:
            hook, patrol.on_stop = patrol.on_stop, None  # this stop is recorded below
            try:
                patrol.stop_patrol()
            finally:
                patrol.on_stop = hook
        self.counters["stops" if word != "disarm" else "disarms"] += 1
        record = LastWord(word, by, self._wall())
        self.last_stop = _stop_text(record)
        level = NOTICE_CRITICAL if force or word == "terminate" else NOTICE_WARNING
        state = "" if was_armed else " (already disarmed)"
        self._notice(level, f"{word}{' (forced)' if force else ''} by {by}{state}")
        self._received(word, session, force)
        await self.remember(record)

    async def remember(self, word: LastWord) -> None:
        """The last word on disk (in a worker thread); in order, the newest last."""
        self.last_word = word
        async with self._saving:
            if self.last_word is not word:
                return  # a newer word was said while this one waited: it is written instead
            try:
                await asyncio.to_thread(self.store.save, word)
            except OSError as exc:
                _LOGGER.error("arming: cannot keep the last word in %s: %s", self.store.path, exc)

    # ------------------------------------------------------------------ hooks

    def _before_patrol_start(self) -> str | None:
        """The patrol's start: arms through the checks; the start becomes the last word."""
        refusal = self.arm("patrol start")
        if refusal is not None:
            return refusal
        self.autostart_pending = False
        self.countdown_until = None
        self._remember_soon(LastWord("start", "patrol start", self._wall()))
        return None

    def _on_patrol_stop(self) -> None:
        self._remember_soon(LastWord("stop", "patrol stop", self._wall()))
        self.last_stop = _stop_text(self.last_word) if self.last_word else ""

    def _remember_soon(self, word: LastWord) -> None:
        # Called synchronously from the patrol: the write runs at the next tick (≤ 100 ms).
        self.last_word = word
        self._unsaved = True
        self._said.set()

    def _on_override(self, state: OverrideState) -> None:
        if state.engaged and not self.armed:
            # Engaging the override is the controller saying "move": it arms, through the
            # manual subset of the checks.
            refusal = self.arm(f"override of {state.station_id}", manual=True)
            if refusal is not None:
                _LOGGER.warning("arming: override engaged but disarmed: %s", refusal)

    def _on_control(self, control: ControlState) -> None:
        # Kept past a release: the authority may free control before this hears the
        # session's end (SESSION_CLOSED's subscribers run in order).
        if control.session_id is not None:
            self._controller_session = control.session_id

    def _on_session_closed(self, event: SessionClosed) -> None:
        """``failsafe.gcs_loss_action = hold``: the controller lost while patrolling holds."""
        if self.ctx.config.failsafe.gcs_loss_action != "hold":
            return
        current = self.ctx.authority.controller
        if event.session_id != self._controller_session or (
            current is not None and current.session_id != event.session_id
        ):
            return  # not the controller's (or control has passed to someone since)
        patrol = self.ctx.patrol
        if patrol is None or patrol.state.value in ("idle", "stopped"):
            return  # nothing started: nothing to hold
        self._notice(NOTICE_CRITICAL, f"ground station lost ({event.station_id}): patrol holds")
        patrol.stop_patrol(operator=False)
        self._remember_soon(LastWord("hold", f"{event.station_id} lost", self._wall()))
        self.last_stop = _stop_text(self.last_word) if self.last_word else ""

    def _on_fix(self, fix: GpsFix) -> None:
        self._fix_at = self._clock()

    def _on_fix_lost(self, lost: GpsFixLost) -> None:
        self._fix_at = None

    def _on_imu(self, status: ImuStatus) -> None:
        self._imu_at = self._clock()

    # ------------------------------------------------------------------ stepping

    async def tick(self) -> None:
        """The autostart's checks and countdown."""
        if not self.autostart_pending:
            return
        now = self._clock()
        reasons = self.reasons()
        if reasons:
            if self.countdown_until is not None:
                self.countdown_until = None
            if reasons != self._announced:
                self._announced = reasons
                self._notice(NOTICE_WARNING, f"autostart waits: {'; '.join(reasons)}")
            return
        countdown = self.ctx.config.arming.countdown_s
        if self.countdown_until is None:
            self.countdown_until = now + countdown
            self._notice(NOTICE_CRITICAL, f"autostart: arming and patrolling in {countdown:.0f} s")
        if now < self.countdown_until:
            return
        self.autostart_pending = False
        self.countdown_until = None
        patrol = self.ctx.patrol
        if patrol is None:
            return
        try:
            patrol.start_patrol()
        except RouteError as exc:
            self._notice(NOTICE_WARNING, f"autostart refused: {exc}")
            return
        self.counters["autostarts"] += 1
        self._notice(NOTICE_NOTICE, "autostart: armed, patrolling")

    # ------------------------------------------------------------------ reports

    def section(self) -> Arming:
        countdown = None
        if self.countdown_until is not None:
            countdown = round(max(0.0, self.countdown_until - self._clock()), 1)
        reasons = self.reasons()
        return Arming(
            armed=self.armed,
            ready=not reasons,
            prearm=reasons,
            countdown_s=countdown,
            last_stop=self.last_stop,
        )

    def _publish(self, reason: str) -> None:
        self.bus.publish(topics.ARMING_STATE, ArmingState(self.armed, reason))

    def _notice(self, severity: int, text: str) -> None:
        _LOGGER.log(logging.WARNING if severity <= NOTICE_WARNING else logging.INFO, "%s", text)
        self.bus.publish(topics.SAFETY_NOTICES, SafetyNotice(severity, text))

    def _received(self, word: str, session: Session | None, force: bool) -> None:
        self.bus.publish(
            topics.COMMAND_RECEIVED,
            CommandReceived(
                "rpc",
                word,
                json.dumps({"force": force}),
                session.session_id if session else None,
                session.station_id if session else None,
                True,
            ),
        )


def _stop_text(word: LastWord) -> str:
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(word.at)) if word.at else "?"
    return f"{word.word} by {word.by} at {when} UTC"


class ArmingMethods:
    """Signaling methods: ``arm`` (control), ``disarm`` and ``stop`` (any session)."""

    def __init__(self, actor: ArmingActor) -> None:
        self.actor = actor

    def register(self, ctx: PlatformContext) -> None:
        ctx.rpc.add("arm", ctx.authority.guard("arm", self.arm))
        ctx.rpc.add("disarm", self.disarm)
        ctx.rpc.add("stop", self.stop)
        ctx.rpc.add("get_arming", self.get_arming)

    async def arm(self, call: CallContext) -> dict[str, Any]:
        refusal = self.actor.arm(who(call.session))
        if refusal is not None:
            raise RpcError(INVALID_PARAMS, f"arming refused: {refusal}")
        return self.get_arming(call)

    async def disarm(self, call: CallContext, force: Any = False) -> dict[str, Any]:
        if call.session is None:
            raise RpcError(INVALID_PARAMS, "disarm needs a session")
        await self.actor.stop(call.session, "disarm", force=bool(force))
        return self.get_arming(call)

    async def stop(self, call: CallContext) -> dict[str, Any]:
        if call.session is None:
            raise RpcError(INVALID_PARAMS, "stop needs a session")
        await self.actor.stop(call.session, "stop")
        return self.get_arming(call)

    def get_arming(self, call: CallContext) -> dict[str, Any]:
        section = self.actor.section()
        return {
            "armed": section.armed,
            "ready": section.ready,
            "prearm": list(section.prearm),
            "countdown_s": section.countdown_s,
            "last_stop": section.last_stop,
        }


async def async_setup(ctx: PlatformContext) -> None:
    configured = ctx.config.arming.state_file
    path = Path(configured) if configured else state_dir() / "last_word.json"
    actor = ArmingActor(ctx, LastWordStore(path))
    await actor.start()
    ctx.arming = actor
    ArmingMethods(actor).register(ctx)
    ctx.telemetry.register(Arming, actor.section)
    ctx.telemetry.add_counters("arming", lambda: actor.counters)
    ctx.supervisor.start(actor)
