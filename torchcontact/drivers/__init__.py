"""Drivers for force/torque sensors: Robotiq FT 300, generic Modbus (RTU/TCP), simulators.

pymodbus and pyserial (the ``drivers`` extra) are imported only when a link is opened, so this
package imports without them.
"""

from torchcontact.drivers.base import (
    ConnectionLost,
    FTConnectionError,
    FTError,
    FTSample,
    FTSource,
    FTStats,
    SampleFlags,
)
from torchcontact.drivers.modbus import ModbusFTSensor
from torchcontact.drivers.profiles import (
    Profile,
    ProfileError,
    available_profiles,
    load_profile,
)
from torchcontact.drivers.robotiq import RobotiqFT300
from torchcontact.drivers.stream import StreamParser, encode_stream_frame

__all__ = [
    "ConnectionLost",
    "FTConnectionError",
    "FTError",
    "FTSample",
    "FTSource",
    "FTStats",
    "ModbusFTSensor",
    "Profile",
    "ProfileError",
    "RobotiqFT300",
    "SampleFlags",
    "StreamParser",
    "available_profiles",
    "encode_stream_frame",
    "load_profile",
]
