"""PX4's parameter set and its MAVLink parameter protocol, for the SITL autopilot.

The protocol (https://mavlink.io/en/services/parameter.html) as PX4's ``mavlink_parameters.cpp``
serves it:

- PARAM_REQUEST_LIST: every parameter as PARAM_VALUE, in index order (``param_index``,
  ``param_count``), the last one last (MAVSDK treats index + 1 == count as the end of the list).
  PX4's leading ``_HASH_CHECK`` value (a cache hint for QGroundControl) is not sent.
- PARAM_REQUEST_READ: by name when ``param_index`` is -1, else by index; PARAM_VALUE back.
- PARAM_SET: accepted only when the declared type matches the parameter's own type
  (``MAV_PARAM_TYPE_INT32`` for an INT32, ``MAV_PARAM_TYPE_REAL32`` for a float); a mismatch
  is refused silently (PX4 logs "invalid param" on its console and answers nothing), an unknown
  name too. An accepted value is echoed as PARAM_VALUE.

Encoding: PX4 copies the 4 bytes of ``param_value`` (a float on the wire) into the parameter
(``param_set(param, &set.param_value)``): an INT32 travels as its own bit pattern ("byte-wise",
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE). A tool that converts the integer to a float
instead ("C-cast", ArduPilot's convention, or pymavlink's ``param_set_send(name, 3, INT32)``)
sends the float 3.0 = 0x40400000 with the INT32 type: PX4 accepts it and stores 1077936128.
That is the well-known ``EKF2_EV_CTRL = 1077936128`` trap, reproduced here byte for byte.

Defaults are PX4 v1.14's (its module.yaml files; v1.15 ships the same for these) for the
parameters PX4 itself ships. They differ by version: EKF2_EV_CTRL is 15 up to v1.15 and 0 from
v1.16 on (PX4 PR 23307); after v1.16 MAV_n_CONFIG gave way to SER_<port>_PROT and MAV_ETH_EN,
and MAV_n_BROADCAST defaults to 1 on every instance (v1.14: 1, 0, 0). The few values that
describe this stub's own links (the Ethernet MAVLink instance of the companion, on the stub's
UDP ports) are set as a board wired that way would have them.

``clamp`` (name -> (lo, hi)) makes the stub keep a written value inside limits of its own and
echo what it kept, as an autopilot whose module constrains a parameter after the write: the
read-back then differs from what was written (configure's MISMATCH).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9

ParamValue = int | float


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One parameter: its name, type (MAV_PARAM_TYPE_INT32 or _REAL32) and default."""

    name: str
    param_type: int
    default: ParamValue


def _i(name: str, default: int) -> ParamSpec:
    return ParamSpec(name, MAV_PARAM_TYPE_INT32, int(default))


def _f(name: str, default: float) -> ParamSpec:
    return ParamSpec(name, MAV_PARAM_TYPE_REAL32, float(default))


# PX4 defaults (ekf2/module.yaml, params_*.yaml, mavlink/module.yaml, serial and commander
# parameters). Alphabetical, as PX4 indexes its parameters.
PX4_DEFAULTS: tuple[ParamSpec, ...] = tuple(
    sorted(
        (
            _i("BAT1_N_CELLS", 4),
            _f("BAT1_V_CHARGED", 4.05),
            _f("BAT1_V_EMPTY", 3.6),
            _i("CAL_ACC0_ID", 1310988),
            _i("CAL_GYRO0_ID", 1310988),
            _i("CAL_MAG0_ID", 197388),
            _i("CAL_MAG0_ROT", -1),
            _i("COM_ARM_WO_GPS", 1),
            _i("COM_RC_IN_MODE", 0),
            _f("COM_DISARM_LAND", 2.0),
            _f("EKF2_ACC_NOISE", 0.35),
            _i("EKF2_BARO_CTRL", 1),
            _f("EKF2_BARO_DELAY", 0.0),
            _f("EKF2_BARO_GATE", 5.0),
            _f("EKF2_BARO_NOISE", 3.5),
            _i("EKF2_DECL_TYPE", 7),
            _f("EKF2_DELAY_MAX", 200.0),
            _i("EKF2_EN", 1),
            _f("EKF2_EVA_NOISE", 0.1),
            _f("EKF2_EVP_GATE", 5.0),
            _f("EKF2_EVP_NOISE", 0.1),
            _f("EKF2_EVV_GATE", 3.0),
            _f("EKF2_EVV_NOISE", 0.1),
            _i("EKF2_EV_CTRL", 15),  # v1.14/v1.15; 0 from v1.16 on
            _f("EKF2_EV_DELAY", 0.0),
            _i("EKF2_EV_NOISE_MD", 0),
            _f("EKF2_EV_POS_X", 0.0),
            _f("EKF2_EV_POS_Y", 0.0),
            _f("EKF2_EV_POS_Z", 0.0),
            _i("EKF2_EV_QMIN", 0),
            _i("EKF2_GPS_CHECK", 245),
            _i("EKF2_GPS_CTRL", 7),
            _f("EKF2_GPS_DELAY", 110.0),
            _f("EKF2_GPS_P_NOISE", 0.5),
            _f("EKF2_GPS_V_NOISE", 0.3),
            _f("EKF2_GYR_NOISE", 0.015),
            _f("EKF2_HDG_GATE", 2.6),
            _f("EKF2_HEAD_NOISE", 0.3),
            _i("EKF2_HGT_REF", 1),
            _i("EKF2_IMU_CTRL", 7),
            _f("EKF2_MAG_DECL", 0.0),
            _f("EKF2_MAG_DELAY", 0.0),
            _i("EKF2_MAG_TYPE", 0),
            _i("EKF2_MULTI_IMU", 0),
            _i("EKF2_MULTI_MAG", 0),
            _i("EKF2_NOAID_TOUT", 5000000),
            _i("EKF2_OF_CTRL", 0),
            _f("EKF2_OF_DELAY", 20.0),
            _i("EKF2_PREDICT_US", 10000),
            _f("EKF2_RNG_A_HMAX", 5.0),
            _f("EKF2_RNG_A_VMAX", 1.0),
            _i("EKF2_RNG_CTRL", 1),
            _f("EKF2_RNG_DELAY", 5.0),
            _f("EKF2_RNG_GATE", 5.0),
            _f("EKF2_RNG_NOISE", 0.05),
            _f("EKF2_RNG_PITCH", 0.0),
            _f("EKF2_RNG_POS_X", 0.0),
            _f("EKF2_RNG_POS_Y", 0.0),
            _f("EKF2_RNG_POS_Z", 0.0),
            _f("EKF2_RNG_QLTY_T", 1.0),
            _f("EKF2_RNG_SFE", 0.01),
            _f("EKF2_TAU_POS", 0.25),
            _f("EKF2_TAU_VEL", 0.25),
            _i("MAV_0_CONFIG", 101),  # TELEM 1: the telemetry radio (ground station)
            _i("MAV_0_FORWARD", 1),
            _i("MAV_0_MODE", 0),  # Normal
            _i("MAV_0_RATE", 1200),
            _i("MAV_1_CONFIG", 0),
            _i("MAV_1_FORWARD", 0),
            _i("MAV_1_MODE", 2),  # Onboard
            _i("MAV_1_RATE", 0),
            _i("MAV_0_BROADCAST", 1),
            _i("MAV_1_BROADCAST", 0),
            _i("MAV_2_BROADCAST", 0),  # v1.14: the stub sends to a fixed port anyway
            _i("MAV_2_CONFIG", 0),
            _i("MAV_2_FORWARD", 0),
            _i("MAV_2_MODE", 0),
            _i("MAV_2_RATE", 0),
            _i("MAV_2_REMOTE_PRT", 14550),
            _i("MAV_2_UDP_PRT", 14550),
            _i("MAV_COMP_ID", 1),
            _i("MAV_SYS_ID", 1),
            _i("MAV_TYPE", 2),
            _f("MPC_XY_VEL_MAX", 12.0),
            _f("MPC_Z_VEL_MAX_DN", 1.5),
            _f("MPC_Z_VEL_MAX_UP", 3.0),
            _i("MPC_ALT_MODE", 0),
            _i("NAV_DLL_ACT", 0),
            _i("NAV_RCL_ACT", 2),
            _i("SENS_EN_TFMINI", 0),
            _i("SER_TEL1_BAUD", 57600),
            _i("SER_TEL2_BAUD", 921600),
            _i("SER_TEL3_BAUD", 57600),
            _i("SER_TEL4_BAUD", 57600),
            _i("SYS_AUTOSTART", 4001),
            _i("SYS_HAS_BARO", 1),
            _i("SYS_HAS_GPS", 1),
            _i("SYS_HAS_MAG", 1),  # a count in newer PX4 (0: none, 2: two magnetometers)
            _i("SYS_HITL", 0),
        ),
        key=lambda s: s.name,
    )
)


def px4_parameters(companion_listen_port: int, companion_remote_port: int) -> list[ParamSpec]:
    """PX4's defaults, with the companion's MAVLink instance as this stub's links are wired:
    instance 2 on Ethernet (MAV_2_CONFIG = 1000), Onboard mode, listening on the stub's
    ``listen_port`` and sending to the companion's port."""
    wired = {
        "MAV_2_CONFIG": 1000,
        "MAV_2_MODE": 2,
        "MAV_2_UDP_PRT": companion_listen_port,
        "MAV_2_REMOTE_PRT": companion_remote_port,
    }
    return [
        ParamSpec(s.name, s.param_type, wired[s.name]) if s.name in wired else s
        for s in PX4_DEFAULTS
    ]


def int32_to_wire(value: int) -> float:
    """The float32 whose 4 bytes are the INT32 ``value`` (byte-wise encoding)."""
    return float(struct.unpack("<f", struct.pack("<i", int(value)))[0])


def wire_to_int32(wire: float) -> int:
    """The INT32 stored in the 4 bytes of the float32 ``wire`` (byte-wise decoding)."""
    return int(struct.unpack("<i", struct.pack("<f", float(wire)))[0])


def as_float32(value: float) -> float:
    """``value`` rounded to float32, as PX4 stores it."""
    return float(struct.unpack("<f", struct.pack("<f", float(value)))[0])


class ParamStore:
    """The parameters of one autopilot: typed values, by name and by index (alphabetical)."""

    def __init__(
        self, specs: list[ParamSpec], clamp: dict[str, tuple[float, float]] | None = None
    ) -> None:
        self._specs = {s.name: s for s in sorted(specs, key=lambda s: s.name)}
        self.clamp = dict(clamp or {})  # name -> (lo, hi): written values kept inside
        self._names = list(self._specs)
        self._values: dict[str, ParamValue] = {
            s.name: (
                int(s.default) if s.param_type == MAV_PARAM_TYPE_INT32 else as_float32(s.default)
            )
            for s in self._specs.values()
        }
        self.sets_accepted = 0
        self.sets_refused = 0

    def __len__(self) -> int:
        return len(self._names)

    def __contains__(self, name: object) -> bool:
        return name in self._specs

    def names(self) -> list[str]:
        """Every name, in index order."""
        return list(self._names)

    def index(self, name: str) -> int:
        """PARAM_VALUE.param_index of a name."""
        return self._names.index(name)

    def name_at(self, index: int) -> str | None:
        """The name at a param_index (None outside the list)."""
        return self._names[index] if 0 <= index < len(self._names) else None

    def type_of(self, name: str) -> int:
        """MAV_PARAM_TYPE_INT32 or MAV_PARAM_TYPE_REAL32."""
        return self._specs[name].param_type

    def get(self, name: str) -> ParamValue:
        """The value (int for INT32, float for REAL32)."""
        return self._values[name]

    def set(self, name: str, value: ParamValue) -> None:
        """Set a value in its own type (the stub's own use, e.g. test set-up)."""
        if self.type_of(name) == MAV_PARAM_TYPE_INT32:
            self._values[name] = int(value)
        else:
            self._values[name] = as_float32(float(value))

    def wire_value(self, name: str) -> float:
        """The value as it travels in PARAM_VALUE.param_value (byte-wise for INT32)."""
        value = self._values[name]
        if self.type_of(name) == MAV_PARAM_TYPE_INT32:
            return int32_to_wire(int(value))
        return float(value)

    def set_from_wire(self, name: str, wire: float, declared_type: int) -> bool:
        """PARAM_SET: store the 4 bytes of ``wire`` when ``declared_type`` matches the
        parameter's type (as PX4 does); False (nothing stored) for an unknown name or a type
        mismatch."""
        if name not in self._specs or declared_type != self.type_of(name):
            self.sets_refused += 1
            return False
        value: ParamValue = (
            wire_to_int32(wire) if declared_type == MAV_PARAM_TYPE_INT32 else as_float32(wire)
        )
        if name in self.clamp:
            lo, hi = self.clamp[name]
            value = type(value)(min(max(value, lo), hi))
        self._values[name] = value
        self.sets_accepted += 1
        return True


def _param_id(raw: Any) -> str:
    """PARAM_* param_id (bytes or str, NUL-padded, not terminated at 16 chars) as a str."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0]


@dataclass(eq=False)
class ParamServer:
    """The parameter protocol on one or more links: ``handle(msg, reply)`` consumes PARAM_*
    messages addressed to this autopilot (system ``system_id``, component ``component_id`` or
    0) and answers through ``reply(message)``."""

    store: ParamStore
    mav: Any  # the link's pymavlink encoder
    system_id: int = 1
    component_id: int = 1
    requests: int = field(default=0, init=False)  # PARAM_* requests served

    def _for_us(self, msg: Any) -> bool:
        return int(msg.target_system) == self.system_id and int(msg.target_component) in (
            self.component_id,
            0,
        )

    def param_value(self, name: str) -> Any:
        """PARAM_VALUE of one parameter."""
        s = self.store
        return self.mav.param_value_encode(
            name.encode("ascii"), s.wire_value(name), s.type_of(name), len(s), s.index(name)
        )

    def handle(self, msg: Any, reply: Callable[[Any], None]) -> bool:
        """True when ``msg`` was a parameter message (answered or deliberately ignored)."""
        kind = msg.get_type()
        if kind not in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
            return False
        if not self._for_us(msg):
            return True
        self.requests += 1
        if kind == "PARAM_REQUEST_LIST":
            for each in self.store.names():
                reply(self.param_value(each))
        elif kind == "PARAM_REQUEST_READ":
            index = int(msg.param_index)
            wanted = _param_id(msg.param_id) if index < 0 else self.store.name_at(index)
            if wanted is not None and wanted in self.store:
                reply(self.param_value(wanted))
        else:
            name = _param_id(msg.param_id)
            if self.store.set_from_wire(name, float(msg.param_value), int(msg.param_type)):
                reply(self.param_value(name))
        return True
