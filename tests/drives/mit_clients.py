"""The published MIT-mode clients, used as their code and docs show, for
``test_mit_clients.py``: each adapter returns what the client would put on the bus (the
8 command bytes) and what it makes of a reply, and nothing of dobhil.

- ``damiao-motor`` 1.0.6: ``DaMiaoMotor(motor_id, feedback_id, bus, motor_type=...)`` on a
  python-can ``virtual`` bus (its README's construction), ``encode_cmd_msg`` and
  ``decode_sensor_feedback`` (no frame is sent: both are pure);
- ``tmotorcancontrol`` 1.2.6: ``TMotorCANControl.mit_can.CAN_Manager``'s static
  ``float_to_uint`` / ``uint_to_float`` and its ``MIT_controller`` / ``parse_MIT_message``
  (instance methods: see :func:`tmotor_unbound`, the one workaround);
- ``mini-cheetah-motor-driver-socketcan`` 0.4.3: ``motor_driver.canmotorlib``'s module
  ``float_to_uint`` / ``uint_to_float``, its firmware tables, and
  ``CanMotorController.send_rad_command`` (clip, axis direction, scale, bit packing, reply
  decoding: the library's own code) with the socket replaced (:class:`SocketlessController`).

Not used: ``tmotor-can-mit-mode`` (its module imports Kvaser's ``canlib`` and opens Kvaser
channel 0 in a class body, at import).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import can
from bitstring import BitArray
from damiao_motor import KD_MAX as DM_KD_MAX
from damiao_motor import KP_MAX as DM_KP_MAX
from damiao_motor import MOTOR_TYPE_PRESETS, DaMiaoMotor
from damiao_motor.core import motor as _dm_motor
from motor_driver import canmotorlib
from TMotorCANControl.mit_can import MIT_Params, CAN_Manager

_CHANNELS = itertools.count()


@dataclass(frozen=True)
class Ranges:
    """A client's table row in one shape: the +- ranges and the gains' maxima."""

    p_max: float
    v_max: float
    t_max: float
    kp_max: float
    kd_max: float
    axis_direction: int = 1


# -- damiao-motor ---------------------------------------------------------------------

def damiao_ranges(motor_type: str) -> Ranges:
    row = MOTOR_TYPE_PRESETS[motor_type]
    assert (row["p_min"], row["v_min"], row["t_min"]) == (-row["p_max"], -row["v_max"], -row["t_max"])
    return Ranges(row["p_max"], row["v_max"], row["t_max"], DM_KP_MAX, DM_KD_MAX)


@contextmanager
def damiao_motor(motor_type: str, motor_id: int = 1) -> Iterator[DaMiaoMotor]:
    """A DaMiaoMotor on its own virtual bus (shut down after)."""
    bus = can.Bus(interface="virtual", channel=f"mit-clients-dm-{next(_CHANNELS)}")
    try:
        yield DaMiaoMotor(motor_id, 0x00, bus, motor_type=motor_type)
    finally:
        bus.shutdown()


# -- tmotorcancontrol -------------------------------------------------------------------

def tmotor_ranges(motor_type: str) -> Ranges:
    row = MIT_Params[motor_type]
    assert (row["P_min"], row["V_min"], row["T_min"], row["Kp_min"], row["Kd_min"]) == (
        -row["P_max"], -row["V_max"], -row["T_max"], 0.0, 0.0)
    return Ranges(row["P_max"], row["V_max"], row["T_max"], row["Kp_max"], row["Kd_max"])


class _ManagerStandIn:
    """What ``MIT_controller`` and ``parse_MIT_message`` use of their ``self``: ``debug``
    and ``send_MIT_message`` (here: kept, not sent)."""

    debug = False

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []

    def send_MIT_message(self, motor_id: int, data: list[int]) -> None:
        self.sent.append((motor_id, bytes(data)))


def tmotor_unbound(method: Callable[..., Any], *args: Any) -> tuple[_ManagerStandIn, Any]:
    """WORKAROUND, the only one for this client: ``CAN_Manager.MIT_controller`` and
    ``parse_MIT_message`` are instance methods, and the class's only way to an instance
    (``__new__``, a singleton) runs ``sudo /sbin/ip link set can0 down/up`` and opens
    socketcan ``can0``; its ``__del__`` runs sudo again (so a subclass would too). Never
    instantiated: the two methods touch only ``self.debug`` and ``self.send_MIT_message``,
    so they are called unbound on a stand-in that has just those (checked by
    ``test_the_tmotor_stand_in_has_what_the_methods_use``)."""
    stand_in = _ManagerStandIn()
    return stand_in, method(stand_in, *args)


def tmotor_command(motor_type: str, p: float, v: float, kp: float, kd: float, t: float,
                   motor_id: int = 1) -> bytes:
    """The 8 bytes ``MIT_controller(motor_id, motor_type, position, velocity, Kp, Kd, I)``
    sends (its ``I`` is the torque's field: it scales it by T_min/T_max)."""
    stand_in, _ = tmotor_unbound(CAN_Manager.MIT_controller, motor_id, motor_type, p, v, kp, kd, t)
    ((sent_to, data),) = stand_in.sent
    assert sent_to == motor_id
    return data


def tmotor_reply(motor_type: str, data: bytes) -> Any:
    """``parse_MIT_message(data, motor_type)``: (position, velocity, current, temperature,
    error); its "current" is the torque field scaled by T_min/T_max, in N m."""
    return tmotor_unbound(CAN_Manager.parse_MIT_message, bytes(data), motor_type)[1]


tmotor_float_to_uint = CAN_Manager.float_to_uint
tmotor_uint_to_float = CAN_Manager.uint_to_float


# -- mini-cheetah-motor-driver-socketcan ----------------------------------------------

#: canmotorlib's firmware tables by its motor_type names (CanMotorController.__init__'s choice)
CANMOTORLIB_TABLES: dict[str, dict[str, float]] = {
    "AK80_6_V1": canmotorlib.AK80_6_V1_PARAMS,
    "AK80_6_V1p1": canmotorlib.AK80_6_V1p1_PARAMS,
    "AK80_6_V2": canmotorlib.AK80_6_V2_PARAMS,
    "AK80_9_V1p1": canmotorlib.AK80_9_V1p1_PARAMS,
    "AK80_9_V2": canmotorlib.AK80_9_V2_PARAMS,
    "AK70_10_V1p1": canmotorlib.AK70_10_V1p1_params,
    "AK10_9_V1p1": canmotorlib.AK10_9_V1p1_PARAMS,
}


def canmotorlib_ranges(motor_type: str) -> Ranges:
    row = CANMOTORLIB_TABLES[motor_type]
    assert (row["P_MIN"], row["V_MIN"], row["T_MIN"], row["KP_MIN"], row["KD_MIN"]) == (
        -row["P_MAX"], -row["V_MAX"], -row["T_MAX"], 0.0, 0.0)
    return Ranges(row["P_MAX"], row["V_MAX"], row["T_MAX"], row["KP_MAX"], row["KD_MAX"],
                  int(row["AXIS_DIRECTION"]))


class SocketlessController(canmotorlib.CanMotorController):
    """WORKAROUND, the only one for this client: ``CanMotorController.__init__`` opens a raw
    AF_CAN socket bound to a SocketCAN interface (none here), and its ``_send_can_frame`` /
    ``_recv_can_frame`` use it. This subclass replaces those three only: the constructor
    makes the same BitArrays as the library's (copied from 0.4.3), sending keeps the frame,
    receiving answers ``reply`` (at once: :func:`canmotorlib_command` sets the library's wait
    for a motor's answer to 0). Everything between -- ``send_rad_command``'s clipping, the
    axis direction, the scaling, the bit packing, ``decode_motor_status`` and
    ``convert_raw_to_physical_rad`` -- is the library's own code."""

    def __init__(self, motor_type: str, reply: bytes = bytes(6), motor_id: int = 1) -> None:
        self.motorParams = CANMOTORLIB_TABLES[motor_type]
        self.motor_id = motor_id
        self.reply = reply
        self.sent: list[bytes] = []
        params = self.motorParams
        self._p_des_BitArray = BitArray(
            uint=canmotorlib.float_to_uint(0, params["P_MIN"], params["P_MAX"], 16), length=16)
        self._v_des_BitArray = BitArray(
            uint=canmotorlib.float_to_uint(0, params["V_MIN"], params["V_MAX"], 12), length=12)
        self._kp_BitArray = BitArray(uint=0, length=12)
        self._kd_BitArray = BitArray(uint=0, length=12)
        self._tau_BitArray = BitArray(uint=0, length=12)
        self._cmd_bytes = BitArray(uint=0, length=64)
        self._recv_bytes = BitArray(uint=0, length=48)

    def _send_can_frame(self, data: bytes) -> None:
        self.sent.append(bytes(data))

    def _recv_can_frame(self) -> tuple[int, int, bytes]:
        return self.motor_id, len(self.reply), self.reply


def canmotorlib_command(motor_type: str, p: float, v: float, kp: float, kd: float, t: float,
                        reply: bytes = bytes(6)) -> tuple[bytes, tuple[float, float, float]]:
    """``send_rad_command(p_des_rad, v_des_rad, kp, kd, tau_ff)``: the 8 bytes it sends and
    what it decodes of ``reply`` (position, velocity, "current": the torque field in N m)."""
    controller = SocketlessController(motor_type, reply)
    # the library busy-waits its module's dt_sleep (0.1 ms) between sending and reading, for
    # a motor to answer; the stand-in socket has the reply at once, so the wait is 0 here
    # (at 0.1 ms it was two thirds of a command's time, 5000 commands a run of the tests)
    wait, canmotorlib.dt_sleep = canmotorlib.dt_sleep, 0.0
    try:
        decoded = controller.send_rad_command(p, v, kp, kd, t)
    finally:
        canmotorlib.dt_sleep = wait
    (data,) = controller.sent
    return data, tuple(decoded)  # type: ignore[return-value]


damiao_float_to_uint = _dm_motor.float_to_uint
damiao_uint_to_float = _dm_motor.uint_to_float
#: damiao-motor's state nibble codes -> its names (DM_MOTOR_*)
DM_STATES: dict[int, str] = dict(_dm_motor._STATE_NAME_MAP)
