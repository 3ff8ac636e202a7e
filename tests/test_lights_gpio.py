"""Lights on GPIO lines through libgpiod v2 (``gpiod``), never sysfs.

No gpiochip, gpio-sim or configfs exists on a build machine: the driver is run against
:class:`platformd.sim.gpio.SimulatedGpio`, which stands in for ``gpiod.request_lines`` at the
boundary, and the first test holds it to the installed gpiod's API so a drift fails here. The
real library is exercised where it can be without hardware: a chip that does not exist.
"""

from __future__ import annotations

import inspect
import threading
from collections.abc import Awaitable, Callable

import gpiod
import pytest
from conftest import quiet_platform_config, wait_until
from gpiod.line import Direction, Value

from brasidas import topics
from brasidas.codecs.commands import MAIN_LIGHTS, POSITIONAL_LIGHTS
from brasidas.config import ConfigError, PlatformConfig, load_config
from brasidas.config.platform import GpioLine
from brasidas.messages import LightsState
from platformd.app import PlatformDaemon
from platformd.motor.gpio import CONSUMER, GpioOutput, LineRequest
from platformd.sim.gpio import SIM_CHIP, SimulatedGpio, SimulatedLineRequest
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]
MISSING_CHIP = "/dev/gpiochip-brasidas-test-missing"


def parameters(function: object) -> list[tuple[str, object]]:
    signature = inspect.signature(function)  # type: ignore[arg-type]
    return [(p.name, p.kind) for p in signature.parameters.values()]


def test_simulated_chip_mirrors_gpiod_v2() -> None:
    assert gpiod.api_version.startswith("2.") or gpiod.__version__.startswith("2.")
    assert parameters(SimulatedGpio.request_lines)[1:] == parameters(gpiod.request_lines)
    public = [name for name in vars(SimulatedLineRequest) if not name.startswith("_")]
    assert public  # every public name of the stand-in is gpiod.LineRequest's, alike
    for name in public:
        ours, theirs = getattr(SimulatedLineRequest, name), getattr(gpiod.LineRequest, name)
        assert isinstance(ours, property) == isinstance(theirs, property), name
        if not isinstance(ours, property):
            assert parameters(ours) == parameters(theirs), name
    # What the driver calls on a request exists on the real one with the same parameters.
    for name in ("set_value", "release"):
        assert parameters(getattr(LineRequest, name)) == parameters(
            getattr(gpiod.LineRequest, name)
        )


def test_simulated_chip_raises_what_libgpiod_raises() -> None:
    gpio = SimulatedGpio()
    output = {17: gpiod.LineSettings(direction=Direction.OUTPUT, output_value=Value.INACTIVE)}
    with pytest.raises(FileNotFoundError):
        gpio.request_lines(MISSING_CHIP, config=output, consumer="t")
    request = gpio.request_lines(SIM_CHIP, config=output, consumer="first")
    with pytest.raises(OSError, match="busy"):
        gpio.request_lines(SIM_CHIP, config=output, consumer="second")
    with pytest.raises(TypeError):
        request.set_value(17, 1)  # type: ignore[arg-type]  # Value, not an int
    request.set_value(17, Value.ACTIVE)
    assert request.get_value(17) is Value.ACTIVE
    assert gpio.holder(SIM_CHIP, 17) == "first"
    request.release()
    assert not request
    assert gpio.holder(SIM_CHIP, 17) is None
    with pytest.raises(gpiod.RequestReleasedError):
        request.set_value(17, Value.INACTIVE)


async def test_a_missing_chip_is_a_clear_error_through_the_real_library() -> None:
    output = GpioOutput(GpioLine(MISSING_CHIP, 17))  # gpiod.request_lines itself
    assert await output.set(True) is False
    assert output.error == (
        f"cannot request GPIO line {MISSING_CHIP}:17: no such GPIO chip (No such file or directory)"
    )
    not_a_chip = GpioOutput(GpioLine("/dev/null", 17))
    assert await not_a_chip.set(True) is False
    assert "not a GPIO character device" in not_a_chip.error
    await output.close()  # nothing was requested: nothing to release


@pytest.mark.parametrize(
    ("value", "chip", "line"),
    [
        ("gpio:/dev/gpiochip0:17", "/dev/gpiochip0", 17),
        ("gpio:gpiochip1:GPIO17", "/dev/gpiochip1", "GPIO17"),
        ("gpio:/dev/gpio/by-name/pinctrl:4", "/dev/gpio/by-name/pinctrl", 4),
    ],
)
def test_gpio_outputs_in_config(value: str, chip: str, line: int | str) -> None:
    config = load_config(PlatformConfig, None, [f"motor.positional_lights_output={value}"])
    assert GpioLine.parse(config.motor.positional_lights_output) == GpioLine(chip, line)


@pytest.mark.parametrize(
    "value",
    ["gpio:/sys/class/gpio/gpio17/value", "gpio:17", "gpio:/dev/gpiochip0:", "gpio:/tmp/x:3"],
)
def test_sysfs_and_malformed_gpio_outputs_are_refused_at_load(value: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(PlatformConfig, None, [f"motor.positional_lights_output={value}"])
    message = str(info.value)
    assert message.startswith("motor.positional_lights_output: must be ")
    assert '"gpio:CHIP:LINE"' in message
    assert value in message


# --------------------------------------------------------------------------- a whole platform


async def lights_command(conn: PlatformConnection, code: int, on: str) -> dict[str, object]:
    answer: dict[str, object] = await conn.call(
        "issue_system_command", group=10, command=code, payload=on
    )
    return answer


async def open_station(daemon: PlatformDaemon, key: bytes) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=key
    )
    await conn.open()
    return conn


async def test_sim_positional_lights_on_a_gpio_line_requested_once_and_off_at_shutdown(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("sim.enabled=true", "motor.enabled=true"), fleet_key
    )
    gpio = daemon.ctx.sim.gpio
    assert gpio is not None
    assert daemon.ctx.positional_lights_output == f"gpio:{SIM_CHIP}:17"
    # Requested at start, as an output driven low, by the platform.
    await wait_until(lambda: gpio.holder(SIM_CHIP, 17) == CONSUMER)
    assert gpio.chips[SIM_CHIP].line(17).direction is Direction.OUTPUT
    assert gpio.value(SIM_CHIP, 17) is Value.INACTIVE
    conn = await open_station(daemon, fleet_key)
    try:
        assert (await lights_command(conn, POSITIONAL_LIGHTS.command, "ON"))["accepted"]
        assert gpio.value(SIM_CHIP, 17) is Value.ACTIVE
        report = await conn.call("get_telemetry_report")
        assert report["lights"] == {"main": False, "positional": True, "errors": {}}
        assert (await lights_command(conn, POSITIONAL_LIGHTS.command, "OFF"))["accepted"]
        assert gpio.value(SIM_CHIP, 17) is Value.INACTIVE
        assert (await lights_command(conn, POSITIONAL_LIGHTS.command, "ON"))["accepted"]
    finally:
        await conn.close()
    requests = [name for name, _ in gpio.calls if name == "request_lines"]
    assert requests == ["request_lines"]  # once, however often it was switched
    # libgpiod is never called on the event loop's thread.
    assert threading.get_ident() not in {thread for _, thread in gpio.calls}
    await daemon.stop()
    # Shutdown: the lit line is driven low (the safe state) and released.
    assert gpio.value(SIM_CHIP, 17) is Value.INACTIVE
    assert gpio.holder(SIM_CHIP, 17) is None
    assert gpio.calls[-1][0] == "release"


async def test_a_busy_line_is_reported_and_refused_then_taken_once_free(
    platform_factory: Factory, fleet_key: bytes, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Another program holds line 18 of the (simulated) chip before the platform starts.
    gpio = SimulatedGpio()
    squatter = gpio.request_lines(
        SIM_CHIP, config={18: gpiod.LineSettings(direction=Direction.OUTPUT)}, consumer="other"
    )
    monkeypatch.setattr("platformd.sim.gpio.SimulatedGpio", lambda: gpio)
    config = quiet_platform_config(
        "sim.enabled=true", "motor.enabled=true", f"motor.main_lights_output=gpio:{SIM_CHIP}:18"
    )
    daemon = await platform_factory(config, fleet_key)
    assert daemon.ctx.sim.gpio is gpio
    busy = f"cannot request GPIO line {SIM_CHIP}:18: line busy, held by another consumer"

    def main_error() -> str:
        state = daemon.bus.last(topics.LIGHTS_STATE)
        return state.errors.get("main", "") if state is not None else ""

    await wait_until(lambda: main_error().startswith(busy))
    conn = await open_station(daemon, fleet_key)
    try:
        report = await conn.call("get_telemetry_report")
        assert report["lights"]["errors"]["main"].startswith(busy)
        refused = await lights_command(conn, MAIN_LIGHTS.command, "ON")
        assert refused["accepted"] is False
        assert str(refused["reason"]).startswith(f"main lights: {busy}")
        assert gpio.holder(SIM_CHIP, 18) == "other"  # never taken from its holder
        squatter.release()
        assert (await lights_command(conn, MAIN_LIGHTS.command, "ON"))["accepted"]
        assert gpio.value(SIM_CHIP, 18) is Value.ACTIVE
        assert gpio.holder(SIM_CHIP, 18) == CONSUMER
        assert daemon.bus.last(topics.LIGHTS_STATE) == LightsState(main=True, errors={})
    finally:
        await conn.close()


async def test_a_missing_chip_leaves_the_platform_running_with_the_reason(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true",
            "motor.enabled=true",
            f"motor.positional_lights_output=gpio:{MISSING_CHIP}:17",
        ),
        fleet_key,
    )
    assert daemon.ctx.sim.gpio is None  # configured: the real libgpiod is asked
    conn = await open_station(daemon, fleet_key)
    try:
        missing = f"cannot request GPIO line {MISSING_CHIP}:17: no such GPIO chip"
        await wait_until(
            lambda: "positional" in getattr(daemon.bus.last(topics.LIGHTS_STATE), "errors", {})
        )
        report = await conn.call("get_telemetry_report")
        assert report["lights"]["errors"]["positional"].startswith(missing)
        refused = await lights_command(conn, POSITIONAL_LIGHTS.command, "ON")
        assert refused["accepted"] is False
        assert missing in str(refused["reason"])
        # The rest of the platform goes on: the controller's main lights still switch.
        await wait_until(
            lambda: getattr(daemon.bus.last(topics.CONTROLLER_STATUS), "connected", False)
        )
        assert (await lights_command(conn, MAIN_LIGHTS.command, "ON"))["accepted"]
        assert daemon.ctx.sim.ax3500 is not None
        assert daemon.ctx.sim.ax3500.device.outputs["C"]
    finally:
        await conn.close()
