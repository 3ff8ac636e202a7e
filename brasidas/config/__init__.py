"""Configuration: TOML files over documented defaults, with command-line overrides.

The generic loader, validator and TOML printer are :mod:`brasidas.config.loader`; the schemas
(every section, key, default and constraint) are :mod:`brasidas.config.platform` and
:mod:`brasidas.config.station`. Loading rejects unknown keys, wrong types and values out of
range with one line naming the key (:class:`ConfigError`); a loaded config is frozen.
"""

from brasidas.config.loader import ConfigError, dump_toml, load_config
from brasidas.config.platform import (
    AudioSection,
    BeaconSection,
    GpsSection,
    ImuSection,
    MotorSection,
    NavCamSection,
    PayloadCameraSection,
    PlatformConfig,
    PlatformSection,
    SecuritySection,
    SignalingSection,
    SimSection,
    TelemetrySection,
    VelocitySection,
)
from brasidas.config.station import (
    ConsoleSection,
    DiscoverySection,
    JoystickSection,
    StationConfig,
    StationMediaSection,
    StationSection,
    TelemetryReceiverSection,
    TeleopSection,
)

__all__ = [
    "AudioSection",
    "BeaconSection",
    "ConfigError",
    "ConsoleSection",
    "DiscoverySection",
    "GpsSection",
    "ImuSection",
    "JoystickSection",
    "MotorSection",
    "NavCamSection",
    "PayloadCameraSection",
    "PlatformConfig",
    "PlatformSection",
    "SecuritySection",
    "SignalingSection",
    "SimSection",
    "StationConfig",
    "StationMediaSection",
    "StationSection",
    "TelemetryReceiverSection",
    "TelemetrySection",
    "TeleopSection",
    "VelocitySection",
    "dump_toml",
    "load_config",
]
