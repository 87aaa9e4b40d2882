"""One drive test suite over every protocol: ODrive (``odrive-0.6``), CiA 402
(``cia402-emulated``), MIT mode (``ak80-9``, a CubeMars AK80-9, and ``dm4310``, a
Damiao DM4310) and moteus over CAN FD (``moteus-r4.11``), each against its emulated drive,
in lockstep and in real time.

What every protocol must do the same way, whatever its frames: the enable and disable
handshakes, a feedback timeout when the drive goes silent, a fault reported the
protocol's own way (ODrive: an Estop; CiA 402: the node's over-torque fault, EMCY 0x8311
with the statusword's fault bit) ending the run as ``drive_fault`` with its code, the
safe stop (zero torque then the disable, confirmed by the drive's status; and the one
loud line when it cannot be confirmed), and the closed loop reaching the force
reference with the same summary fields.

What a protocol cannot do is its drive's declared capability, checked, never a skip: a
CubeMars AK in MIT mode answers the exit frame with a reply that carries no mode, so its
drive declares ``confirms_disable`` False. Its safe stop must then be
``Confirmation.UNCONFIRMABLE`` once the reply to the exit came with zero torque -- a NOTE
saying so when the run lasted its duration, the loud line at a fault or a signal -- and
``NOT_ACKNOWLEDGED``, loud, when the exit went unanswered; everything else of a safe stop
still holds and is checked on the emulated motor: zero torque last, the exit frame sent,
the motor out of motor mode with zero torque. (The Damiao's reply carries its state: its
exit is confirmed like an ODrive's.)

What differs per protocol is data, in :class:`Protocol`: the profile, the design delay
the run must take from it (CiA 402 applies each command at the next SYNC, an MIT motor
answers each command with the next cycle's feedback: one whole period,
``command_delay_periods``; checked, never set by the test), which frames carry feedback
and commands, how to read the host's commands off the bus, and how to inject its fault
(MIT: the motor's own over-current trip, error 2 / state 0xA, provoked by a command whose
kp term demands far more than its range; moteus: replies saying mode 1 with fault 38, over
temperature, as a controller reports it). Faults are :mod:`dobhil.emulator.faults` wrappers chosen by frame id; the two
that need a CiA 402 payload are small :class:`~dobhil.emulator.faults.Fault` subclasses
here. ODrive-only behaviour stays in ``test_drive_emulated.py`` and ``tests/runtime/``.

Nothing asserts wall-clock timing: lockstep counts simulated steps; real-time runs are
checked on what they reached and on counts the run measured itself.
"""

from __future__ import annotations

import dataclasses
import itertools
import re
import struct
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml

from dobhil.config import Config
from dobhil.drives import DriveState, load_profile, make_drive
from dobhil.drives.base import Confirmation, Drive
from dobhil.drives.cia402.codec import PowerState
from dobhil.drives.mit import codec as mit_codec
from dobhil.drives.mit.codec import Special
from dobhil.drives.mit.rules import model_of
from dobhil.drives.moteus import codec as moteus_codec
from dobhil.drives.moteus.frames import reply_values
from dobhil.drives.registry import protocol as drive_protocol
from dobhil.drives.periodic import native_periodic
from dobhil.errors import DriveError
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, Firmware
from dobhil.emulator.plant import Plant
from dobhil.emulator.faults import Direction, Fault, InjectFrame, LoseSent, SilenceAfter, faulty
from dobhil.drives.emulated import EmulatedDrive, LockstepBus
from dobhil.drives.registry import make_emulated_drive
from dobhil.runtime.loop import RunResult, StopRequest
from dobhil.runtime.session import RunSession, summary
from dobhil.runtime.stop import StopReason

from tests.runtime.helpers import (DRIVERS, summary_shape, REALTIME_SLACK, STEP_FROM_ZERO, Sniffer, demo_config,
                               finite_tail, realtime_profile, wait_until)

AT = 100            # a fault strikes around the 100th cycle of a 0.4 s run
_CHANNELS = itertools.count()


# ---------------------------------------------------------------------------
# Per-protocol data


@dataclass(frozen=True)
class Commands:
    """What the host commanded the drive on the bus, in order."""

    torques: list[float]   # [Nm] (CiA 402: per mille / 1000 of the 1 Nm rated torque; MIT: the
                           # code's value, the zero command's code as 0.0)
    states: list[int]      # ODrive: requested axis states; CiA 402: controlwords; MIT: special frames


@dataclass(frozen=True)
class Protocol:
    name: str                          # the shipped profile
    node: int
    design_delay: int                  # whole periods the design must assume (the demo: 0)
    feedback_ids: frozenset[int]       # frames whose silence is a feedback timeout
    active_state: int                  # the emulator's axis_state when it follows torque
    idle_states: frozenset[int]        # the emulator's axis_state once disabled
    stopped_states: frozenset[int]     # ... or once stopped by a fault of its own
    last_states: tuple[int, ...]       # the host's final state commands of a safe stop
    fault_words: tuple[str, ...]       # what the stop line of its fault says
    decode: Callable[[Sequence[can.Message]], Commands]
    fault: Callable[[], list[Fault]]   # the protocol's fault, injected around cycle AT
    lose_disable: Callable[[], list[Fault]]   # the drive never sees the disable
    torque_quantum: float              # [Nm] resolution of the torque command on the wire
    no_answer: str                     # the enable's line when nobody answers (a regex)
    #: [s] the enable's own deadline in that case
    no_answer_enable_timeout: float = 0.3
    profile_changes: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: what its drive declares it can do: confirm that the drive left torque control
    confirms_disable: bool = True
    #: the feedback only answers the host's commands (MIT): the loop runs on host timing
    requests_feedback: bool = False
    #: the drive's frames its start-up must hear before the enable frames go out (CiA 402:
    #: the SDO answers of its set-up); none of them says what state the drive is in
    startup_ids: frozenset[int] = frozenset()

    def __str__(self) -> str:
        return self.name


# -- ODrive (CAN Simple) ---------------------------------------------------------

_OD_NODE = 3
_OD_TORQUE = codec.arbitration_id(_OD_NODE, CmdId.SET_INPUT_TORQUE)
_OD_AXIS_STATE = codec.arbitration_id(_OD_NODE, CmdId.SET_AXIS_STATE)


def _odrive_commands(frames: Sequence[can.Message]) -> Commands:
    torques, states = [], []
    for msg in frames:
        if msg.is_remote_frame or msg.arbitration_id not in (_OD_TORQUE, _OD_AXIS_STATE):
            continue
        decoded = codec.decode_message(msg, Firmware.V0_6)
        if msg.arbitration_id == _OD_TORQUE:
            torques.append(decoded.torque_nm)
        else:
            states.append(int(decoded.requested_state))
    return Commands(torques, states)


ODRIVE = Protocol(
    name="odrive-0.6", node=_OD_NODE, design_delay=0,
    feedback_ids=frozenset({codec.arbitration_id(_OD_NODE, CmdId.GET_ENCODER_ESTIMATES)}),
    active_state=int(AxisState.CLOSED_LOOP_CONTROL), idle_states=frozenset({int(AxisState.IDLE)}),
    stopped_states=frozenset({int(AxisState.IDLE)}),
    last_states=(int(AxisState.IDLE),), fault_words=("ESTOP_REQUESTED",),
    decode=_odrive_commands,
    fault=lambda: [InjectFrame(codec.encode(codec.Estop(), node_id=_OD_NODE, firmware=Firmware.V0_6),
                               after=0, ids={_OD_TORQUE})],
    lose_disable=lambda: [LoseSent(frames=1, ids={_OD_AXIS_STATE})],
    torque_quantum=2.0 ** -23,                 # float32 at 1 N m
    no_answer=r"^no heartbeat from node 4 within 0.3 s",
    profile_changes={"watchdog_timeout": 0},   # else its watchdog would disable it anyway
)


# -- CiA 402 (CST over CANopen) ---------------------------------------------------

_C_NODE = 5
_C_RPDO = 0x200 + _C_NODE
_C_TPDO1, _C_TPDO2 = 0x180 + _C_NODE, 0x280 + _C_NODE
_RPDO = struct.Struct("<Hh")          # controlword U16, target torque I16 (per mille)
_QUICK_STOP, _DISABLE_VOLTAGE = 0x02, 0x00
#: the emulator's axis_state: the power state's code (dobhil.drives.cia402.codec)
OPERATION_ENABLED, SWITCH_ON_DISABLED, FAULT = (int(PowerState.OPERATION_ENABLED),
                                                int(PowerState.SWITCH_ON_DISABLED),
                                                int(PowerState.FAULT))


def _cia402_commands(frames: Sequence[can.Message]) -> Commands:
    torques, words = [], []
    for msg in frames:
        if msg.arbitration_id == _C_RPDO and len(msg.data) == _RPDO.size:
            word, per_mille = _RPDO.unpack(msg.data)
            torques.append(per_mille / 1000.0)
            if not words or words[-1] != word:
                words.append(word)
    return Commands(torques, words)


class OverTorque(Fault):
    """The host's torque commands ask for more than the drive's max torque (0x6072 = 3000
    per mille), SYNC after SYNC: the node's own over-torque fault (EMCY 0x8311, fault bit,
    after 3 of them). Zero-torque RPDOs (the safe stop's) pass as sent."""

    direction = Direction.SEND

    def __init__(self, *, per_mille: int = 3500) -> None:
        super().__init__((_C_RPDO,))
        self.per_mille = per_mille

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if len(msg.data) != _RPDO.size:
            return (msg,)
        word, torque = _RPDO.unpack(msg.data)
        if torque == 0:
            return (msg,)
        self.applied += 1
        return (_with_data(msg, _RPDO.pack(word, self.per_mille)),)


class LoseControlwords(Fault):
    """RPDOs carrying one of ``words`` are lost on the way: the node never sees the
    quick stop or the disable voltage (it still gets the zero torque)."""

    direction = Direction.SEND

    def __init__(self, words: frozenset[int]) -> None:
        super().__init__((_C_RPDO,))
        self.words = words

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if len(msg.data) == _RPDO.size and _RPDO.unpack(msg.data)[0] in self.words:
            self.applied += 1
            return ()
        return (msg,)


def _with_data(msg: can.Message, data: bytes) -> can.Message:
    return can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                       is_extended_id=msg.is_extended_id, dlc=len(data), data=bytearray(data))


CIA402 = Protocol(
    name="cia402-emulated", node=_C_NODE,
    design_delay=1,   # the RPDO is applied at the next SYNC: the profile's command_delay_periods
    feedback_ids=frozenset({_C_TPDO2}),   # the motion event; TPDO1 (statusword) keeps coming
    active_state=OPERATION_ENABLED, idle_states=frozenset({SWITCH_ON_DISABLED}),
    stopped_states=frozenset({SWITCH_ON_DISABLED, FAULT}),
    last_states=(_QUICK_STOP, _DISABLE_VOLTAGE), fault_words=("0x8311",),
    decode=_cia402_commands,
    fault=lambda: [OverTorque()],
    lose_disable=lambda: [LoseControlwords(frozenset({_QUICK_STOP, _DISABLE_VOLTAGE}))],
    torque_quantum=1e-3,                       # 1 per mille of the 1 N m rated torque
    no_answer=r"^node 6: SDO 0x1018:01 \(.*\) timed out after 0.3 s \(reached: pre-operational\)$",
    # well above the profile's sdo_timeout (0.3 s): the unanswered SDO, not the enable's
    # deadline, ends it, even when opening the CANopen session is slow on a loaded machine
    no_answer_enable_timeout=2.0,
    startup_ids=frozenset({0x580 + _C_NODE}),   # SDO server -> client
)


# -- MIT mode (CubeMars AK80-9, Damiao DM4310) -------------------------------------

_MIT_ZERO = mit_codec.Command(0.0, 0.0, 0.0, 0.0, 0.0)


def _mit_profile(name: str) -> tuple[int, int, mit_codec.MitModel]:
    """The shipped profile's node id, reply id and model row."""
    profile = load_profile(name)
    return profile.node_id, int(profile.options.get("reply_id", 0)), model_of(profile)


def _mit_commands(name: str) -> Callable[[Sequence[can.Message]], Commands]:
    node, _, model = _mit_profile(name)
    zero = mit_codec.pack_command(model, _MIT_ZERO)

    def decode(frames: Sequence[can.Message]) -> Commands:
        torques, states = [], []
        for msg in frames:
            if msg.arbitration_id != node or msg.is_remote_frame or len(msg.data) != 8:
                continue
            data = bytes(msg.data)
            special = mit_codec.is_special(data)
            if special is not None:
                states.append(int(special))
            elif data == zero:   # the wire cannot say 0 N m exactly: the zero command's code
                torques.append(0.0)
            else:
                torques.append(mit_codec.unpack_command(model, data).torque)
        return Commands(torques, states)

    return decode


class OverCurrent(Fault):
    """The host's torque commands become a stiff position command (kp at its top, the
    position at the far end of the range): the motor's torque law demands far more than
    its range, its own over-current trip (CubeMars error 2, Damiao state 0xA). Zero-torque
    commands (the safe stop's) and special frames pass as sent."""

    direction = Direction.SEND

    def __init__(self, name: str) -> None:
        node, _, self.model = _mit_profile(name)
        super().__init__((node,))
        self.zero = mit_codec.pack_command(self.model, _MIT_ZERO)
        m = self.model
        self.stiff = mit_codec.pack_command(m, mit_codec.Command(m.p_max, 0.0, m.kp_max, 0.0, 0.0))

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        data = bytes(msg.data)
        if len(data) != 8 or data == self.zero or mit_codec.is_special(data) is not None:
            return (msg,)
        self.applied += 1
        return (_with_data(msg, self.stiff),)


class LoseSpecial(Fault):
    """Special frames of ``kinds`` to the node are lost on the way (the motor never
    leaves motor mode); its commands pass."""

    direction = Direction.SEND

    def __init__(self, name: str, kinds: frozenset[Special]) -> None:
        super().__init__((_mit_profile(name)[0],))
        self.kinds = kinds

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if mit_codec.is_special(bytes(msg.data)) in self.kinds:
            self.applied += 1
            return ()
        return (msg,)


def _mit(name: str, *, confirms_disable: bool, fault_words: tuple[str, ...]) -> Protocol:
    node, reply_id, model = _mit_profile(name)
    return Protocol(
        name=name, node=node,
        design_delay=1,   # the reply to cycle k's command is cycle k+1's feedback: command_delay_periods
        feedback_ids=frozenset({reply_id}),
        active_state=1, idle_states=frozenset({0}), stopped_states=frozenset({0}),   # motor mode / rest
        last_states=(int(Special.EXIT),), fault_words=fault_words,
        decode=_mit_commands(name),
        fault=lambda: [OverCurrent(name)],
        lose_disable=lambda: [LoseSpecial(name, frozenset({Special.EXIT}))],
        torque_quantum=model.quanta.torque,      # 2 t_max / 4095
        no_answer=rf"^no reply from node {node + 1} .*not in MIT mode",
        confirms_disable=confirms_disable, requests_feedback=True,
    )


MIT_CUBEMARS = _mit("ak80-9", confirms_disable=False, fault_words=("error 2", "over current"))
MIT_DAMIAO = _mit("dm4310", confirms_disable=True, fault_words=("over current",))


# -- moteus (mjbots r4.11, CAN FD) ---------------------------------------------------

_M_NODE = 1
_M_COMMAND = moteus_codec.arbitration_id(0, _M_NODE, reply=True)
_M_REPLY = moteus_codec.arbitration_id(_M_NODE, 0, reply=False)
_M_STOP = bytes.fromhex("010000")   # write mode 0, the stop


def _moteus_commands(frames: Sequence[can.Message]) -> Commands:
    """Feedforward torques of the mode-10 commands, and each change of the mode written."""
    torques: list[float] = []
    modes: list[int] = []
    for msg in frames:
        if msg.arbitration_id != _M_COMMAND:
            continue
        writes = {s.register: s.value for s in moteus_codec.parse(bytes(msg.data))
                  if s.opcode is moteus_codec.Opcode.WRITE}
        mode = writes.get(moteus_codec.Register.MODE)
        if mode is None:
            continue
        if int(mode) == moteus_codec.Mode.POSITION:
            torques.append(float(writes[moteus_codec.Register.COMMAND_FEEDFORWARD_TORQUE] or 0.0))
        if not modes or modes[-1] != int(mode):
            modes.append(int(mode))
    return Commands(torques, modes)


class OverTemperature(Fault):
    """The controller's replies say mode 1 (fault) with fault code 38, over temperature, as
    the firmware reports it (the reply's mode and fault registers rewritten) until a stop,
    which clears a fault (``registers.md`` 0x000)."""

    direction = Direction.RECV

    def __init__(self) -> None:
        super().__init__((_M_REPLY,))

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        data = bytearray(msg.data)
        values = reply_values(bytes(data))
        if values.get(moteus_codec.Register.MODE) != moteus_codec.Mode.POSITION or \
                moteus_codec.Register.FAULT not in values:
            return (msg,)   # a stop clears a fault: the replies to it say mode 0 as sent
        self.applied += 1
        data[2] = moteus_codec.Mode.FAULT                                # "21 00 <mode>" leads the reply
        fault_at = bytes(data).index(bytes((0x21, moteus_codec.Register.FAULT)))
        data[fault_at + 2] = moteus_codec.Fault.OVER_TEMPERATURE
        return (can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                            is_extended_id=msg.is_extended_id, is_fd=True, bitrate_switch=msg.bitrate_switch,
                            data=data),)


class LoseStops(Fault):
    """The stop frames (mode 0) are lost on the way; the torque commands pass."""

    direction = Direction.SEND

    def __init__(self) -> None:
        super().__init__((_M_COMMAND,))

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if bytes(msg.data[:3]) == _M_STOP:
            self.applied += 1
            return ()
        return (msg,)


MOTEUS = Protocol(
    name="moteus-r4.11", node=_M_NODE,
    design_delay=1,   # the reply to cycle k's command is cycle k+1's feedback: command_delay_periods
    feedback_ids=frozenset({_M_REPLY}),
    active_state=int(moteus_codec.Mode.POSITION), idle_states=frozenset({int(moteus_codec.Mode.STOPPED)}),
    stopped_states=frozenset({int(moteus_codec.Mode.STOPPED)}),
    last_states=(int(moteus_codec.Mode.STOPPED),), fault_words=("38", "OVER_TEMPERATURE"),
    decode=_moteus_commands,
    fault=lambda: [OverTemperature()],
    lose_disable=lambda: [LoseStops()],
    torque_quantum=2.0 ** -23,                 # float32 at 1 N m (command_resolution f32)
    no_answer=rf"^no reply from node {_M_NODE + 1} on id 0x{(_M_NODE + 1) << 8:X} ",
    requests_feedback=True,
)

PROTOCOLS = {p.name: p for p in (ODRIVE, CIA402, MIT_CUBEMARS, MIT_DAMIAO, MOTEUS)}


class HearOnly(Fault):
    """Every frame the host receives is lost except ``keep``: a drive whose status and
    motion frames never reach the host (a wrong reply id, a receive path that is broken),
    while the host's frames still reach the drive."""

    def __init__(self, keep: frozenset[int]) -> None:
        super().__init__(None)
        self.keep = keep

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if msg.arbitration_id in self.keep:
            return (msg,)
        self.applied += 1
        return ()


class Armed(Fault):
    """``inner`` acts only once armed, from the run's cycle AT on (:class:`ArmAt`): the run
    says when a fault strikes, not the number of frames its start-up happened to take."""

    def __init__(self, inner: Fault) -> None:
        super().__init__(None)
        self.inner = inner
        self.direction = inner.direction  # type: ignore[misc]
        self.armed = False

    def __call__(self, msg: can.Message, now: float) -> Sequence[can.Message]:
        return self.inner(msg, now) if self.armed else (msg,)

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        raise AssertionError("Armed delegates in __call__")


@dataclass
class ArmAt:
    """A cycle sink arming ``faults`` after cycle ``at``."""

    faults: Sequence[Fault]
    at: int = AT
    #: set at cycle ``at`` too: the run stopped as by SIGINT
    request: StopRequest | None = None

    def started(self, fb: Any) -> None:
        pass

    def cycle(self, k: int, *args: Any) -> None:
        if k >= self.at:
            for fault in self.faults:
                if isinstance(fault, Armed):
                    fault.armed = True
            if self.request is not None and not self.request.is_set():
                self.request.set("SIGINT")

    def stop(self, stop: Any) -> None:
        pass
TIMINGS = ("lockstep", "realtime")


@pytest.fixture(params=list(PROTOCOLS))
def protocol(request: pytest.FixtureRequest) -> Protocol:
    return PROTOCOLS[request.param]


@pytest.fixture(params=TIMINGS)
def timing(request: pytest.FixtureRequest) -> str:
    return str(request.param)


# ---------------------------------------------------------------------------
# Drive level: the handshakes against the emulated drive


@dataclass
class Rig:
    drive: Drive
    emu: EmulatedDrive
    host: can.BusABC
    lockstep: bool

    def wait_for(self, predicate: Callable[[], bool]) -> bool:
        """Let the emulator run until ``predicate`` (lockstep: simulated steps, a bound of
        2 s of drive time; real time: a bound for a loaded machine)."""
        if not self.lockstep:
            return wait_until(predicate)
        for _ in range(2000):
            if predicate():
                return True
            self.drive.poll(0.001)
        return predicate()


@contextmanager
def drive_rig(protocol: Protocol, timing: str, *, drive_node: int | None = None,
              **profile_changes: Any) -> Iterator[Rig]:
    """The protocol's drive against its emulated drive on a private virtual channel
    (lockstep: behind a LockstepBus, on its simulated clock; real time: the emulator's
    thread). ``drive_node``: the node id the host addresses (default: the emulator's)."""
    channel = f"drive-suite-{next(_CHANNELS)}"
    profile = dataclasses.replace(load_profile(protocol.name),
                                  **{"bus": {}, "enable_timeout": 2.0, **profile_changes})
    # a CAN FD protocol's channel is opened as CAN FD (its drive refuses a classic bus)
    fd = {"protocol": can.CanProtocol.CAN_FD} if drive_protocol(profile.protocol).fd else {}
    host_bus = can.Bus(interface="virtual", channel=channel, **fd)
    config = demo_config(f"drive.profile={protocol.name}")
    emu = make_emulated_drive(can.Bus(interface="virtual", channel=channel, **fd), profile,
                              Plant.from_config(config))
    host: can.BusABC = host_bus
    clock: dict[str, Any] = {}
    if timing == "lockstep":   # an MIT motor streams nothing: the loop's period is the step
        host = LockstepBus(host_bus, [emu], dt=profile.feedback_period or config.loop.period)
        clock["clock"] = host.clock  # type: ignore[attr-defined]
    else:
        emu.start()
    host_profile = profile if drive_node is None else dataclasses.replace(profile, node_id=drive_node)
    drive = make_drive(host, host_profile, **clock)
    try:
        yield Rig(drive, emu, host, timing == "lockstep")
    finally:
        drive.disable()
        getattr(drive, "close", lambda: None)()
        if host is not host_bus:
            host.shutdown()
        emu.close()
        host_bus.shutdown()


@pytest.fixture
def rig(protocol: Protocol, timing: str) -> Iterator[Rig]:
    with drive_rig(protocol, timing) as made:
        yield made


def test_enable_then_disable_handshake(rig: Rig, protocol: Protocol) -> None:
    rig.drive.enable()
    assert rig.drive.status.state is DriveState.ENABLED
    assert rig.emu.protocol_state == protocol.active_state  # type: ignore[attr-defined]
    assert rig.drive.disable() is True
    assert rig.drive.status.state is DriveState.DISABLED
    assert rig.wait_for(lambda: rig.emu.protocol_state in protocol.idle_states  # type: ignore[attr-defined]
                        and rig.emu.applied_torque == 0.0)


def expected_confirmation(drive: Drive, protocol: Protocol) -> Confirmation:
    """CONFIRMED, or UNCONFIRMABLE for a drive that declares it cannot confirm -- and the
    declaration must be the protocol's (a drive cannot opt out of confirming)."""
    assert drive.confirms_disable is protocol.confirms_disable
    return Confirmation.CONFIRMED if protocol.confirms_disable else Confirmation.UNCONFIRMABLE


def test_enable_again_after_a_disable(rig: Rig, protocol: Protocol) -> None:
    rig.drive.enable()
    rig.drive.send_torque(0.1)
    rig.drive.poll(0.01)
    report = rig.drive.safe_stop()
    assert report.confirmation is expected_confirmation(rig.drive, protocol), report.detail
    assert rig.wait_for(lambda: rig.emu.protocol_state in protocol.idle_states)  # type: ignore[attr-defined]
    rig.drive.enable()
    assert rig.emu.protocol_state == protocol.active_state  # type: ignore[attr-defined]


def test_a_drive_that_never_answers_fails_the_enable_in_one_line(protocol: Protocol,
                                                                  timing: str) -> None:
    """The host addresses a node id nobody has: the enable ends in one line naming the
    node and what was awaited (ODrive: its heartbeat; CiA 402: the first SDO answer, with
    the object), and the emulated drive at the other id never left its idle state."""
    with drive_rig(protocol, timing, drive_node=protocol.node + 1,
                   enable_timeout=protocol.no_answer_enable_timeout) as made:
        with pytest.raises(DriveError) as info:
            made.drive.enable()
        line = str(info.value)
        assert "\n" not in line and re.search(protocol.no_answer, line), line
        assert made.drive.status.state is not DriveState.ENABLED
        assert made.emu.protocol_state != protocol.active_state  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------
# Run level: every stop of a run, in lockstep and in real time


def profile_ref(tmp_path: Path, protocol: Protocol, timing: str, **changes: Any) -> str:
    """The shipped profile in lockstep; real time: a copy with the drive's waits relaxed
    for a loaded machine (rates unchanged). A copy elsewhere names its files (CiA 402:
    the EDS) by absolute path."""
    if timing == "lockstep" and not changes:
        return protocol.name
    return str(realtime_profile(tmp_path, protocol.name, **_located(protocol), **changes))


def _located(protocol: Protocol) -> dict[str, Any]:
    shipped = yaml.safe_load((DRIVERS / f"{protocol.name}.yaml").read_text(encoding="utf-8"))
    section = shipped.get("cia402")
    if section is None:
        return {}
    return {"cia402": {**section, "eds": str(DRIVERS / section["eds"])}}


#: [s] a real-time drive's wait for a disable answer that never comes, where that wait is its
#: enable wait (no heartbeat to time it: MIT, moteus; dobhil/drives/base.py): the shipped
#: profiles' 0.5 s and a margin, not the 2 s :func:`realtime_profile` gives an enable on a
#: loaded machine -- a test that waits the silence out waits this long for nothing
SILENCE_WAIT = 0.6


def silence_waited(protocol: Protocol, timing: str) -> dict[str, Any]:
    """The profile changes of a test whose drive never answers the disable: the wait
    :data:`SILENCE_WAIT` where the enable wait is the disable's (real time only)."""
    if timing != "realtime" or load_profile(protocol.name).heartbeat_period:
        return {}
    return {"enable_timeout": SILENCE_WAIT}


def suite_config(tmp_path: Path, protocol: Protocol, timing: str, *overrides: str,
                 step: bool = True, **profile_changes: Any) -> Config:
    """The analysed loop (``step``: contact from the start, 1 N m step; else the demo's
    own reference), 0.4 s, on the protocol's profile and design delay."""
    profile = profile_ref(tmp_path, protocol, timing, **profile_changes)
    slack = REALTIME_SLACK if timing == "realtime" else ()
    host = ("loop.timing=host",) if protocol.requests_feedback else ()   # nothing streams to time on
    return demo_config(f"drive.profile={profile}", *(STEP_FROM_ZERO if step else ()),
                       "loop.duration=0.4", *slack, *host, *overrides)


@dataclass
class Outcome:
    result: RunResult
    commands: Commands
    settled: bool
    summary: dict[str, Any]
    final: tuple[int, float]     # the emulator's axis_state and applied torque at the end
    confirms_disable: bool       # what the run's drive declared
    frames: list[can.Message]    # every frame on the bus, in the order sent
    faults: list[Fault]          # the run's faults: those from the start, then the armed ones


#: runs of one real-time check at most: a run the machine starved, stopped as ``host_too_slow``
#: by the run itself (the host or the emulated drive not scheduled for longer than the drive's
#: watch or the feedback timeout allows), ended before what the check is about could happen,
#: and is made again; a stop the run blamed on anything else is never made again
STARVED_RUNS = 3


def run(config: Config, protocol: Protocol, timing: str, faults: Callable[[], Sequence[Fault]] = list, *,
        armed: Callable[[], Sequence[Fault]] = list, settle: bool = True, signal: bool = False) -> Outcome:
    """Run with the emulated drive, the faults ``faults()`` makes from the start and those
    ``armed()`` makes from cycle AT on (``signal``: a stop requested at cycle AT, as SIGINT
    does); ``settle``: then wait for it to be out of torque control with zero torque (real
    time: a bound; False where it must not be). Real time: up to :data:`STARVED_RUNS` runs,
    each with new faults, while the run says ``host_too_slow`` (the last such run is the
    outcome: the check fails on it)."""
    for _ in range(STARVED_RUNS if timing == "realtime" else 1):
        out = _run_once(config, protocol, timing, list(faults()), list(armed()), settle=settle, signal=signal)
        if out.result.stop.reason is not StopReason.HOST_TOO_SLOW:
            break
    return out


def _run_once(config: Config, protocol: Protocol, timing: str, faults: list[Fault],
              armed: list[Fault], *, settle: bool, signal: bool) -> Outcome:
    wrapped = [*faults, *(Armed(f) for f in armed)]
    request = StopRequest()
    with RunSession(config, emulate=True, lockstep=timing == "lockstep",
                    sink=ArmAt(wrapped, request=request if signal else None), stop_request=request,
                    bus_wrapper=faulty(*wrapped) if wrapped else None) as session, \
            Sniffer(session.bus_spec.channel) as sniffer:
        # the design delay comes from the protocol (its profile), not from the test
        design = session.design_config.design
        assert (design.delay_samples, design.input_delay) == (protocol.design_delay, 0.0)
        result = session.run()
        emu = session.emulator
        assert emu is not None

        def idle() -> bool:
            return emu.protocol_state in protocol.stopped_states and emu.applied_torque == 0.0  # type: ignore[union-attr]

        if timing == "lockstep":
            emu.handle_pending()  # type: ignore[union-attr]
            settled = idle()
        else:
            settled = wait_until(idle) if settle else idle()
        final = (int(emu.protocol_state), float(emu.applied_torque))  # type: ignore[union-attr]
        frames = sniffer.drain()
        return Outcome(result, protocol.decode(frames), settled, summary(session, result),
                       final, session.drive.confirms_disable, list(frames), [*faults, *armed])


def assert_stopped_safely(out: Outcome, protocol: Protocol, reason: StopReason,
                          words: Sequence[str] = (), *, status_silenced: bool = False) -> None:
    """Why in one line; zero torque was the last torque; the disable commands last; the
    drive confirmed it -- or, where the protocol declares it cannot, it answered: a NOTE at
    the run's planned end, the loud line at any other -- and ended out of torque control
    with zero torque. ``status_silenced``: the frames that would confirm (or answer) were
    silenced with the feedback (an MIT reply is both): the loud line, whatever the drive."""
    stop, report = out.result.stop, out.result.safe_stop
    line = stop.line()
    assert stop.reason is reason, line
    assert "\n" not in line
    for word in words:
        assert word.lower() in line.lower(), (word, line)
    assert out.commands.torques and out.commands.torques[-1] == 0.0, out.commands.torques[-3:]
    assert tuple(out.commands.states[-len(protocol.last_states):]) == protocol.last_states, \
        out.commands.states
    assert out.confirms_disable is protocol.confirms_disable
    if protocol.confirms_disable and status_silenced:
        assert report is not None and report.confirmation is Confirmation.NOT_ACKNOWLEDGED, report
        assert report.sent and not out.result.disabled
        warning = report.warning()
        assert warning.startswith(f"drive may still be enabled: node {protocol.node} did not acknowledge ")
        assert warning.endswith("; cut power") and out.summary["drive_warning"] == warning
    elif protocol.confirms_disable:
        assert report is not None and report.confirmation is Confirmation.CONFIRMED, report
        assert out.result.disabled and report.warning() == "" and out.summary["drive_warning"] == ""
    elif status_silenced:   # no reply to the exit: not acknowledged at all, loud
        assert report is not None and report.confirmation is Confirmation.NOT_ACKNOWLEDGED, report
        assert report.sent and not out.result.disabled and report.note() == ""
        warning = report.warning()
        assert warning.startswith(f"drive may still be enabled: node {protocol.node} did not answer exit motor mode ")
        assert out.summary["drive_warning"] == warning and out.summary["drive_note"] == ""
    else:   # every frame went out and was answered; nothing the drive sends can say it worked: never "safe"
        assert report is not None and report.confirmation is Confirmation.UNCONFIRMABLE, report
        assert report.sent and not report.safe and not out.result.disabled
        assert re.match(r"a reply to each safe-stop frame, the last \(to exit motor mode\) with torque [-+]\d\.\d{4} "
                        r"N m \(zero\), but the exit cannot be confirmed: ", report.detail), report.detail
        assert report.planned is (reason is StopReason.DONE)
        if report.planned:   # the run's own end: a note of what was confirmed, no loud line
            assert report.warning() == "" and out.summary["drive_warning"] == ""
            assert report.note().startswith(f"node {protocol.node} cannot confirm its disable by design: ")
            assert out.summary["drive_note"] == report.note()
        else:   # a fault or a signal: the same account, loudly
            assert report.note() == "" and out.summary["drive_note"] == ""
            assert_unconfirmable_line(report.warning(), protocol)
            assert out.summary["drive_warning"] == report.warning()
        assert out.summary["drive_disabled"] is False
    assert out.settled, f"emulated drive not out of torque control with zero torque: {out.final}"


def assert_unconfirmable_line(warning: str, protocol: Protocol) -> None:
    """The one loud line of a drive that cannot confirm its disable: names the node and
    says that it cannot be confirmed, and to cut power."""
    assert warning.startswith(f"drive may still be enabled: node {protocol.node} "), warning
    assert re.search(r"cannot (be )?confirm", warning) and warning.endswith("; cut power") and "\n" not in warning


def test_run_that_lasts_its_duration_stops_safely(tmp_path: Path, protocol: Protocol,
                                                 timing: str) -> None:
    out = run(suite_config(tmp_path, protocol, timing), protocol, timing)
    assert_stopped_safely(out, protocol, StopReason.DONE, ["ran 0.4 s"])
    # every one of its 400 cycles ran or was skipped (real time on a busy machine skips
    # the frames that came while a cycle was late, and counts each late cycle as an
    # overrun): no count of cycles the run itself did not measure
    result = out.result
    counts = (result.cycles, result.skipped, result.overruns)
    assert result.cycles > 0 and result.cycles + result.skipped == 400, counts
    # a skip comes only after an overrun, and each overrun skips at least one deadline or
    # frame, but the run's last cycle: late, it has no deadline left to skip
    flags = result.trace["overrun"]
    last_late = len(flags) == 400 and flags[-1] == 1.0
    assert result.overruns > 0 or result.skipped == 0, counts
    assert result.skipped >= result.overruns - last_late, (counts, last_late)
    if timing == "lockstep":
        assert result.cycles == 400


def test_feedback_timeout_when_the_drive_goes_silent(tmp_path: Path, protocol: Protocol,
                                                     timing: str) -> None:
    """Feedback timing stops in the cycle that waited in vain; host timing (MIT) runs on
    with the last feedback until it is older than ``loop.feedback_timeout``. An MIT reply
    is the motor's status too: silenced, nothing can confirm the exit either."""
    config = suite_config(tmp_path, protocol, timing, **silence_waited(protocol, timing))
    out = run(config, protocol, timing, armed=lambda: [SilenceAfter(frames=0, ids=protocol.feedback_ids)])
    silence = out.faults[0]
    assert_stopped_safely(out, protocol, StopReason.FEEDBACK_TIMEOUT, ["no fresh feedback"],
                          status_silenced=protocol.requests_feedback)
    assert out.result.stop.cycle > AT and silence.applied > 0
    if timing == "lockstep":
        stale = round(config.loop.feedback_timeout / config.loop.period) if protocol.requests_feedback else 0
        assert out.result.stop.cycle == AT + 1 + stale


def test_fault_the_protocols_way_is_a_drive_fault(tmp_path: Path, protocol: Protocol,
                                                  timing: str) -> None:
    out = run(suite_config(tmp_path, protocol, timing), protocol, timing, armed=protocol.fault)
    assert_stopped_safely(out, protocol, StopReason.DRIVE_FAULT, protocol.fault_words)
    # before the run's 400 cycles were up, counted on the drive's clock (the host's may
    # lag behind it on a busy machine)
    assert AT < out.result.stop.cycle < 400


def test_unconfirmed_safe_stop_says_so_loudly(tmp_path: Path, protocol: Protocol,
                                              timing: str) -> None:
    config = suite_config(tmp_path, protocol, timing, **protocol.profile_changes,
                          **silence_waited(protocol, timing))
    out = run(config, protocol, timing, protocol.lose_disable, settle=False)
    report = out.result.safe_stop
    assert out.result.stop.reason is StopReason.DONE
    assert report is not None and report.sent and not out.result.disabled
    warning = report.warning()
    if protocol.confirms_disable:
        assert report.confirmation is Confirmation.NOT_ACKNOWLEDGED
        assert warning.startswith(f"drive may still be enabled: node {protocol.node} did not acknowledge ")
        assert warning.endswith("; cut power") and "\n" not in warning
    else:   # the zero torque was answered, the exit was not: loud, even at the planned end
        assert out.confirms_disable is False and report.confirmation is Confirmation.NOT_ACKNOWLEDGED
        assert report.planned and report.note() == ""
        # the zero torque's reply carries the run's last torque; replies to the run's own
        # commands that the host had not read yet when the stop began come too (real time: one,
        # or several when the machine was too busy to run the motor or the host meanwhile)
        said = re.match(rf"drive may still be enabled: node {protocol.node} did not answer exit motor mode "
                        r"\((\d+) repl(y|ies) to 2 safe-stop frames, the last with torque [-+]\d\.\d{4} N m "
                        r"\(not zero\); no answer within [0-9.]+ s\)", warning)
        # the replies the host read after its zero torque, as counted on this very bus (never
        # a count assumed of the machine): at least the zero torque's own
        read = replies_after_the_zero_torque(out.frames, protocol)
        assert said and int(said.group(1)) == read >= 1, (read, warning)
        assert warning.endswith("; cut power") and "\n" not in warning
    assert out.summary["drive_warning"] == warning and out.summary["drive_disabled"] is False
    assert out.commands.torques[-1] == 0.0 and not out.settled   # still in torque control


def replies_after_the_zero_torque(frames: Sequence[can.Message], protocol: Protocol) -> int:
    """The motor's replies (MIT: on ``feedback_ids``) on the bus after the host's last zero
    torque command, the safe stop's. Real time, the private channel gets each frame as the
    host sends or reads it (dobhil/runtime/session.py), so these are the replies the host
    read after it sent the zero torque."""
    zero_torque = max(i for i, msg in enumerate(frames)
                      if msg.arbitration_id == protocol.node and protocol.decode([msg]).torques == [0.0])
    return sum(msg.arbitration_id in protocol.feedback_ids for msg in frames[zero_torque + 1:])


def test_a_drive_sent_its_enable_but_never_heard_is_loud(tmp_path: Path, protocol: Protocol,
                                                        timing: str) -> None:
    """The enable frames went out and reached the drive, but nothing it sent ever reached
    the host: the enable fails, and the safe stop cannot call the drive "never seen, never
    enabled" -- it may have taken the enable -- so every protocol ends with the loud line,
    ``drive_disabled`` false, although the disable frames went out and did their work."""
    config = suite_config(tmp_path, protocol, timing, enable_timeout=protocol.no_answer_enable_timeout)
    out = run(config, protocol, timing, lambda: [HearOnly(protocol.startup_ids)])
    deaf = out.faults[0]
    stop, safe_stop = out.result.stop, out.result.safe_stop
    assert stop.reason is StopReason.ENABLE_FAILED, stop.line()
    assert safe_stop is not None and safe_stop.sent and deaf.applied > 0
    assert safe_stop.confirmation is Confirmation.NEVER_ANSWERED and not safe_stop.safe, safe_stop
    assert not out.result.disabled and out.summary["drive_disabled"] is False
    assert out.summary["safe_stop"]["confirmation"] == "never_answered"
    warning = safe_stop.warning()
    assert warning.startswith(f"drive may still be enabled: node {protocol.node} never answered: its enable "
                              "frames (for "), warning
    assert warning.endswith("cannot be confirmed; cut power") and "\n" not in warning, warning
    assert out.summary["drive_warning"] == warning and out.summary["drive_note"] == ""
    # the disable frames went out last, and the drive that got them is out of torque control
    assert tuple(out.commands.states[-len(protocol.last_states):]) == protocol.last_states, out.commands.states
    assert out.settled, out.final


def test_a_signal_stops_safely_and_loudly_where_unconfirmed(tmp_path: Path, protocol: Protocol,
                                                             timing: str) -> None:
    """A stop requested mid-run (SIGINT's way): the safe stop as ever; a drive that cannot
    confirm its disable by design gives the loud line, not the note, although it answered."""
    out = run(suite_config(tmp_path, protocol, timing), protocol, timing, signal=True)
    assert_stopped_safely(out, protocol, StopReason.SIGNAL, ["SIGINT"])
    assert AT <= out.result.stop.cycle < 400


def test_closed_loop_reaches_the_force_reference(tmp_path: Path, protocol: Protocol,
                                                 timing: str) -> None:
    """Demo loop (contact from 5 mrad away at 0.2 N m, then a step to 1 N m at 0.6 s):
    the TRUE interaction torque settles on the reference, the estimate agrees. The bound
    owes nothing to the run's own spread, so a loop that oscillates fails it: at rest on the
    environment the force loop's integral action puts the estimate on the reference (float
    rounding apart), and the true interaction torque is the torque the drive applies, the
    command rounded to the protocol's torque quantum on the wire: every sample of the last
    100 ms (or of the last 10 cycles that ran, when a host the machine did not schedule
    skipped those 100 ms) within half a quantum of 1 N m. The step settles into that band
    by 0.77 s in lockstep and in real time alike (the plant moves on the drive's clock; a
    busy host skips cycles, never the equilibrium), the tail starts at 0.9 s."""
    config = suite_config(tmp_path, protocol, timing, "loop.duration=1.0", step=False)
    out = run(config, protocol, timing)
    assert_stopped_safely(out, protocol, StopReason.DONE)
    assert out.result.cycles + out.result.skipped == 1000
    tr = out.result.trace
    tail_true = finite_tail(tr["tau_int_true"], tr["t"], 0.1)
    tail_hat = finite_tail(tr["tau_int_hat"], tr["t"], 0.1)
    assert tail_true.size >= 10 and tr["tau_ref"][-1] == 1.0
    float_rounding = 1e-9   # sums of a few hundred float64 terms of 1 N m (1e-13 seen)
    for tail, band in ((tail_true, protocol.torque_quantum / 2), (tail_hat, 0.0)):
        worst = float(np.max(np.abs(tail - 1.0)))
        assert worst <= band + float_rounding, (worst, band)


def test_summary_has_the_same_fields_for_every_protocol(tmp_path: Path) -> None:
    shapes = {}
    for protocol in PROTOCOLS.values():
        out = run(suite_config(tmp_path, protocol, "lockstep", "loop.duration=0.05"), protocol,
                  "lockstep")
        assert out.result.stop.reason is StopReason.DONE
        shapes[protocol.name] = summary_shape(out.summary)
    odrive = shapes["odrive-0.6"]
    for name, other in shapes.items():
        assert other.keys() == odrive.keys(), name
        assert other == odrive, name


# ---------------------------------------------------------------------------
# The fault wrapper keeps a protocol's periodic frames where they belong


def test_fault_wrapper_forwards_periodic_send_to_the_bus_it_wraps() -> None:
    """FaultyBus is as native as its inner bus; the periodic SYNC is the inner bus's (send
    faults do not drop it), its echo passes the receive faults."""
    from .cia402_node import PumpBus, TestNode402

    channel = f"drive-suite-{next(_CHANNELS)}"
    node = TestNode402(can.Bus(interface="virtual", channel=channel), _C_NODE)
    pumped = PumpBus(channel, node)
    seen: list[float] = []
    node.network.subscribe(0x80, lambda can_id, data, t: seen.append(t))
    lose_all_sync = LoseSent(frames=0, ids={0x80})
    drop_echo = SilenceAfter(frames=0, ids={0x80})
    wrapper = faulty(lose_all_sync, drop_echo)(pumped)
    plain = faulty()(can.Bus(interface="virtual", channel=channel + "-plain"))
    try:
        assert native_periodic(wrapper) and not native_periodic(plain)
        task = wrapper.send_periodic(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False),
                                     0.001)
        assert wrapper.recv(0.0105) is None          # echoes dropped by the receive fault
        assert seen == pytest.approx([0.001 * k for k in range(1, 11)])   # yet every SYNC went out
        assert drop_echo.applied == 10 and lose_all_sync.applied == 0
        task.stop()
    finally:
        plain.shutdown()
        plain._inner.shutdown()  # type: ignore[attr-defined]
        wrapper.shutdown()
        pumped.shutdown()
        node.close()
