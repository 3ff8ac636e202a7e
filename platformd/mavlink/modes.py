"""The vehicle's MAVLink identity and its modes, mapped one to one onto Brasidas's.

The vehicle says it is ArduPilot (``MAV_AUTOPILOT_ARDUPILOTMEGA``) and a ground rover, on
purpose: that one choice makes the three clients agree on mode numbers and names. MAVProxy
names modes from pymavlink's ArduRover table, QGroundControl picks its ArduRover plugin (the
same table; sequence 0 of a mission is home), and MAVSDK's ``start_mission`` sends
``MAV_CMD_DO_SET_MODE`` with ArduRover's AUTO (10). With ``MAV_AUTOPILOT_GENERIC`` MAVSDK would
send PX4's custom modes and QGroundControl would name none. The cost: QGroundControl's
ArduRover plugin expects ArduPilot's parameters; it gets ours (read-only) and warns about the
ones it misses.

=====================  ==============  =================================================
Brasidas               ArduRover mode  meaning
=====================  ==============  =================================================
manual override        MANUAL (0)      the controlling station drives (MANUAL_CONTROL)
patrolling             AUTO (10)       the patrol drives the route (mission)
holding / stopped      HOLD (4)        nobody drives: the motors hold at zero
going to home          RTL (11)        the patrol drives to home through the planner, stops
going to a point       GUIDED (15)     the same to a ground station's point (DO_REPOSITION,
                                       SET_POSITION_TARGET_GLOBAL_INT); set alone: holds
=====================  ==============  =================================================
"""

from __future__ import annotations

import enum

from pymavlink.dialects.v20 import ardupilotmega as mavlink

VEHICLE_TYPE = mavlink.MAV_TYPE_GROUND_ROVER
AUTOPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
VEHICLE_COMPONENT = mavlink.MAV_COMP_ID_AUTOPILOT1
CAMERA_COMPONENT = mavlink.MAV_COMP_ID_CAMERA


class FlightMode(enum.IntEnum):
    """ArduRover's custom mode numbers of the three Brasidas modes."""

    MANUAL = 0
    HOLD = 4
    AUTO = 10
    RTL = 11
    GUIDED = 15


def mode_named(custom_mode: int) -> FlightMode | None:
    """The mode of a custom mode number, None for any other (ACRO, GUIDED, RTL, ...)."""
    try:
        return FlightMode(custom_mode)
    except ValueError:
        return None


CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
)
"""What AUTOPILOT_VERSION claims: only what the endpoint does (no FTP, no rally, no
parameter writes). Integer parameters are sent as their value cast to float (ArduPilot's
encoding), and the bit says so."""
