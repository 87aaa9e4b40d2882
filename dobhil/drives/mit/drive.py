"""MIT-mode actuator (CubeMars/T-Motor AK, Damiao DM-J, Mini-Cheetah firmware) over CAN.

Ranges, reply layout and special frames come from the profile's row of the model table
(:mod:`dobhil.drives.mit.models`, ``drivers/mit-models.yaml``); the bytes from the pure
codec (:mod:`dobhil.drives.mit.codec`). Commands go to the node's id, replies come on
``mit.reply_id`` (the firmware's CAN master id) with the node in byte 0 (Damiao: in the low
nibble, the state in the high one).

Timing: the motor does not stream. It answers every frame with one reply, sampled when it
applies the frame: the reply to cycle k's command is cycle k+1's feedback
(``feedback_streams`` is False: the loop runs on host timing; the profile's
``command_delay_periods: 1`` puts that period into the design).

Enable: queued replies are read first (:meth:`MitDrive._prepare`: a reply that was on its
way before the enter frame must not confirm it), then, with ``reset_faults`` and a model
that has it, clear error (0xFB), then enter motor mode (0xFC), then zero-torque commands
(kp = kd = 0: a frame that never moves the motor) until a reply confirms: any reply to us
for a CubeMars or Mini-Cheetah (their replies carry no mode), state 1 (enabled) for a
Damiao. A motor that is not in MIT mode answers nothing: the timeout's line says so.

Torque: one preallocated command frame, p = v = kp = kd = 0, whose torque bits the codec's
:class:`~dobhil.drives.mit.codec.TorqueFrame` refills (the motor applies
``kp (p - q) + kd (v - dq) + t_ff`` = ``t_ff``).

Decode: each reply to us gives a :class:`MotionEvent` -- the position unwrapped across the
+-P_MAX wrap into a continuous angle (``position_at_limit: wrap``), the velocity -- and a
:class:`StateEvent` with the error code and its text (CubeMars byte 7; Damiao a state
nibble >= 8); a non-zero code faults a run (``drive_fault`` with its text). With
``position_at_limit: saturate`` a reply on the rail (code 0 or 65535) is a fault: the
angle beyond it is lost. The unwrap state lives in the decoder, so replaying the recorded
replies (:meth:`Drive.apply`) rebuilds it.

Safe stop (the base's): zero torque, then exit motor mode (0xFD), each attempted on its
own. A Damiao's reply to the exit says state 0: confirmed. A CubeMars or Mini-Cheetah reply
carries no mode, so nothing can confirm the exit; what it can show is checked instead
(:meth:`MitDrive._disable_answer`): a reply to each safe-stop frame arrived, and the last
one -- the reply to the exit, carrying the torque applied since the zero command -- shows
zero torque. Then the report is :attr:`~dobhil.drives.base.Confirmation.UNCONFIRMABLE`
(a note at a planned end, the loud line at any other); no reply to the exit is
NOT_ACKNOWLEDGED, loud always.

Set zero (0xFE) is never sent here: only ``dobhil check --set-zero`` does it
(:func:`dobhil.drives.mit.preflight.set_zero`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import can

from dobhil.drives.base import Clock, Drive, DriveEvent, HostTimeout, MotionEvent, StateEvent
from dobhil.drives.mit.codec import MitModel, Reply, Special, TorqueFrame, pack_command, special_frame, unpack_reply
from dobhil.drives.mit.replies import ZERO_COMMAND, MitFault, lost_communication_codes, reply_node, state_of
from dobhil.drives.mit.rules import MIT_RULES, check_mit_profile, model_of
from dobhil.drives.profile import DriveProfile, ProtocolRules
from dobhil.drives.waits import Cancel
from dobhil.errors import CodecError, DriveFaultError

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = ["MitDrive"]

_NO_EVENTS: tuple[DriveEvent, ...] = ()


class MitDrive(Drive):
    protocol: ClassVar[str] = "mit"
    active_state_text: ClassVar[str] = "motor mode"
    disabled_state_text: ClassVar[str] = "exit motor mode"
    profile_rules: ClassVar[ProtocolRules] = MIT_RULES

    def __init__(self, bus: can.BusABC, profile: DriveProfile, *, clock: Clock = time.monotonic,
                 reset_faults: bool = False) -> None:
        super().__init__(bus, profile, clock=clock, reset_faults=reset_faults)
        # a profile built in code did not pass the rules' whole-profile check: same lines
        check_mit_profile(profile, f"drive profile {profile.name or profile.protocol!r}")
        self._model = model_of(profile)
        self._model.build_tables()   # before the first command, not in it
        self._reply_id = int(profile.options.get("reply_id", 0))
        # the 16-bit position rolls over: the decoded value then jumps by 2^16 steps
        self._span = self._model.wrap_period
        self._half = self._span / 2
        self._wraps = self._model.position_at_limit == "wrap"
        self._rail = (1 << 16) - 1   # the position's last code: 16 bits
        # hot path: one preallocated zero command whose torque bits are refilled
        self._torque = TorqueFrame(self._model)
        self._torque_msg = self._message(pack_command(self._model, ZERO_COMMAND))
        self._keepalive = self._message(pack_command(self._model, ZERO_COMMAND))
        self._states: dict[tuple[int, int], StateEvent] = {}
        self._lost_communication = lost_communication_codes(self._model)
        # unwrap state: the last reading in the motor's range and whole spans crossed
        self._last_reading: float | None = None
        self._turns = 0

    # -- public ---------------------------------------------------------------

    @property
    def model(self) -> MitModel:
        return self._model

    @property
    def frame_ids(self) -> frozenset[int]:
        """Commands to the node id, replies on ``mit.reply_id``."""
        return frozenset({self.node_id, self._reply_id})

    @property
    def feedback_streams(self) -> bool:
        """Never: each reply answers one command (host timing)."""
        return False

    @property
    def confirms_disable(self) -> bool:
        """Only a layout with a state (Damiao) says the motor left motor mode."""
        return self._has_state()

    @classmethod
    def preflight_probe(cls, profile: DriveProfile) -> PreflightProbe:
        from dobhil.drives.mit.preflight import MitPreflight
        return MitPreflight(profile)

    # -- hooks ----------------------------------------------------------------

    def _message(self, data: bytes) -> can.Message:
        return can.Message(arbitration_id=self.node_id, data=bytearray(data), is_extended_id=False)

    def _special(self, kind: Special) -> can.Message:
        return self._message(special_frame(kind))

    def _prepare(self, deadline: float, cancel: Cancel | None) -> None:
        self._read_queued(deadline)

    def _enable_start(self) -> Sequence[can.Message]:
        frames = []
        if self._reset_faults and Special.CLEAR_ERROR in self._model.special:
            frames.append(self._special(Special.CLEAR_ERROR))
        frames.append(self._special(Special.ENTER))
        return tuple(frames)

    def _enable_step(self, event: StateEvent) -> Sequence[can.Message]:
        """A fault in a reply ends the enable at once (with ``reset_faults`` a Damiao's
        reply to the clear may still show it: then the wait goes on for state 1)."""
        if event.error_code in (MitFault.AT_RAIL, MitFault.BAD_LAYOUT):
            raise DriveFaultError(f"node {self.node_id}: {event.error_text}")
        if event.error_code != 0 and not (self._reset_faults and Special.CLEAR_ERROR in self._model.special):
            hint = (" (dobhil run --reset-faults sends clear error first)"
                    if Special.CLEAR_ERROR in self._model.special else "")
            raise DriveFaultError(f"node {self.node_id} reports error {event.error_text}, {event.state_text}{hint}")
        return ()

    def _keepalive_frames(self) -> Sequence[can.Message]:
        """A zero-torque command (kp = kd = 0), never one that moves the motor: each asks
        for a reply."""
        return (self._keepalive,)

    def _disable_frames(self) -> Sequence[can.Message]:
        return (self._special(Special.EXIT),)

    def _torque_frame(self, tau_nm: float) -> can.Message:
        self._torque.fill(self._torque_msg.data, tau_nm)
        return self._torque_msg

    def _host_watch_of(self, event: StateEvent | None) -> HostTimeout | None:
        """The motor's command timeout (the model row's ``command_timeout``) when its
        replies can say it fired (a Damiao's state 0xD, communication lost), reported in
        the reply to the next command; a motor that only zeroes its command (Mini-Cheetah)
        reports nothing to classify."""
        timeout = self._model.command_timeout
        if not timeout or not self._lost_communication or \
                (event is not None and event.error_code not in self._lost_communication):
            return None
        return HostTimeout("command timeout", timeout)

    def _unconfirmable_detail(self) -> str:
        m = self._model
        return (f"the exit cannot be confirmed: a {m.vendor} {m.model} reply "
                f"(firmware {m.firmware!r}) carries no motor mode")

    def _disable_answer(self, received: Sequence[can.Message], sent: int) -> tuple[bool, str]:
        """Done when a reply came to each of the ``sent`` safe-stop frames (the motor answers
        every frame, in order) and the last -- the reply to the exit, whose torque is what
        the motor applied since the zero command -- shows zero torque: the zero command's
        own value (:attr:`MitModel.torque_bias`) within one step of the reply's torque."""
        replies = [r for r in map(self._reply_of, received) if r is not None]
        if not replies:
            return False, ""
        torque, count = replies[-1].torque, len(replies)
        zero = abs(torque - self._model.torque_bias) <= self._model.quanta.torque
        said = f"torque {torque:+.4f} N m ({'zero' if zero else 'not zero'})"
        if count >= sent and zero:
            return True, f"a reply to each safe-stop frame, the last (to {self.disabled_state_text}) with {said}"
        # which frame a reply answers is not in it: a reply on its way before the stop may
        # be among them, so only the count and the last torque are said
        return False, f"{count} {'reply' if count == 1 else 'replies'} to {sent} safe-stop frames, the last with {said}"

    def _reply_of(self, msg: can.Message) -> Reply | None:
        try:
            return unpack_reply(self._model, msg.data)
        except CodecError:
            return None

    def _fault_text(self, event: StateEvent) -> str:
        if event.error_code in (MitFault.AT_RAIL, MitFault.BAD_LAYOUT):
            return f"node {self.node_id}: {event.error_text}"
        if event.error_code:
            return f"node {self.node_id} fault: error {event.error_text}, {event.state_text}"
        return f"node {self.node_id} left motor mode: {event.state_text}"

    def _enable_timeout_text(self, wait: float) -> str:
        if self._last_state is not None:
            return super()._enable_timeout_text(wait)
        vendor = " (CubeMars: set MIT mode with the vendor's tool)" if self._model.vendor == "cubemars" else ""
        return (f"no reply from node {self.node_id} on id 0x{self._reply_id:X} within {wait:g} s after enter "
                f"motor mode: a motor not in MIT mode answers nothing{vendor}; else check the bus bit rate, "
                f"node_id {self.node_id}, mit.reply_id and the motor's power")

    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        if msg.arbitration_id != self._reply_id or msg.is_extended_id or msg.is_remote_frame \
                or msg.is_error_frame:
            return _NO_EVENTS
        data = msg.data
        if reply_node(self._model, data) != self.node_id:
            return _NO_EVENTS   # another motor's reply on the shared master id
        try:
            reply = unpack_reply(self._model, data)
        except CodecError:
            return (self._layout_fault(len(data)),)
        if not self._wraps and reply.raw_position in (0, self._rail):
            return (MotionEvent(reply.position, reply.velocity), self._rail_fault(reply))
        return (MotionEvent(self._unwrap(reply.position), reply.velocity), self._state_event(reply))

    # -- decoding -------------------------------------------------------------

    def _unwrap(self, reading: float) -> float:
        """A continuous angle from readings that wrap at +-P_MAX (a jump of more than half
        the span between two replies is a crossing of the wrap); saturating readings are
        returned as they are."""
        if not self._wraps:
            return reading
        last = self._last_reading
        if last is not None:
            step = reading - last
            if step > self._half:
                self._turns -= 1
            elif step < -self._half:
                self._turns += 1
        self._last_reading = reading
        return reading + self._turns * self._span

    def _has_state(self) -> bool:
        return bool(self._model.layout.state_field)   # Damiao: the state in the high nibble

    def _state_event(self, reply: Reply) -> StateEvent:
        """The reply's state as an event: one per (error, state) pair, made once (the same
        few pairs come with every reply: no text is formatted per cycle)."""
        key = (reply.error, reply.state)
        event = self._states.get(key)
        if event is None:
            active, words = state_of(self._model, reply)
            error = max(reply.error, 0)
            text = f"{error} ({reply.error_text})" if error else "0 (none)"
            event = StateEvent(active=active, error_code=error, watchdog_tripped=False, state_text=words,
                               error_text=text, state=reply.state)
            self._states[key] = event
        return event

    def _rail_fault(self, reply: Reply) -> StateEvent:
        side = "+" if reply.raw_position else "-"
        text = (f"position at the end of the encodable range ({side}{self._model.p_max:g} rad): the reading "
                "saturates there and the angle beyond it is lost")
        return StateEvent(active=False, error_code=MitFault.AT_RAIL, watchdog_tripped=False,
                          state_text="on the position rail", error_text=text, state=reply.state)

    def _layout_fault(self, length: int) -> StateEvent:
        text = (f"a reply of {length} bytes, which the {self._model.vendor} {self._model.model} layout "
                f"(firmware {self._model.firmware!r}) does not have: the profile's model row does not match the "
                "motor")
        return StateEvent(active=False, error_code=MitFault.BAD_LAYOUT, watchdog_tripped=False,
                          state_text="unknown reply layout", error_text=text)
