"""A moteus controller (mjbots) over CAN FD, commanded in torque by position mode.

Frames (:mod:`dobhil.drives.moteus.frames`): every frame is CAN FD with the bit rate
switch (``moteus:bitrate_switch``), on the arbitration id the official library uses
(``destination | source << 8 | 0x8000 | prefix << 16``; extended when above 0x7ff) and
asks for a reply. The controller answers each frame once, on ``node << 8 | source``,
with the registers the frame's query names, sampled when it applies the frame: the reply
to cycle k's command is cycle k+1's feedback (``feedback_streams`` is False: host timing;
the profile's ``command_delay_periods: 1`` puts that period into the design).

Torque: mode 10 (position) with position NaN, velocity 0, kp scale = kd scale = 0 and the
torque as feedforward (``docs/guides/control-modes.md``, "Torque Control"), the watchdog
timeout register 0x027 in the same frame (``watchdog_timeout`` of the profile; 0 there
writes NaN, no watchdog). One preallocated message whose torque bytes are refilled.

Enable: what is queued is read first; with ``reset_faults`` a stop (mode 0, which clears
a fault) goes first; then zero-torque commands until a reply says mode 10 with no fault.
A controller in mode 1 (fault) ends the enable with the fault's text unless
``reset_faults``; one in mode 11 (the watchdog expired earlier: only a stop leaves it,
``docs/troubleshooting/timeout-mode-11.md``) is sent a stop and the command again.

Decode: each reply to us gives a :class:`MotionEvent` (revolutions of the output shaft
to radians; the controller's position is multi-turn, so nothing wraps; a reading on an
integer resolution's rail or NaN is a fault: the angle beyond it is lost) and a
:class:`StateEvent` whose state is the mode; the fault register counts as an error only
in mode 1 (codes 96 and up name an active limiter in normal modes). Mode 1 or 11 during a
run faults it (``drive_fault`` with the fault's name, or the watchdog's words).

Safe stop (the base's): zero torque, then a stop (mode 0) confirmed by a reply saying
mode 0. The bus must be opened with CAN FD: a bus whose ``protocol`` (python-can
``can.CanProtocol``) says classic CAN is refused when the drive is made (one line).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import can

from dobhil.drives.base import Clock, Drive, DriveEvent, HostTimeout, MotionEvent, StateEvent
from dobhil.drives.moteus.codec import SCALINGS, Mode, Parser, Quantity, Register, Resolution, arbitration_id
from dobhil.drives.moteus.frames import CommandFrame, Query, reply_values, stop_payload
from dobhil.drives.moteus.rules import MOTEUS_RULES, resolution
from dobhil.drives.moteus.states import fault_text, mode_text
from dobhil.drives.plugin import require_fd_bus
from dobhil.drives.profile import DriveProfile, ProtocolRules
from dobhil.drives.waits import Cancel
from dobhil.errors import CodecError, DriveFaultError

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = ["MoteusDrive"]

_NO_EVENTS: tuple[DriveEvent, ...] = ()
_TAU = 2.0 * math.pi
#: codes of dobhil's own: a reply whose position is unusable
POSITION_LOST = 0x100
BAD_REPLY = 0x101
_MAX_CODE = (0x7F, 0x7FFF, 0x7FFFFFFF)


class MoteusDrive(Drive):
    protocol: ClassVar[str] = "moteus"
    active_state_text: ClassVar[str] = "POSITION"
    disabled_state_text: ClassVar[str] = "STOPPED"
    profile_rules: ClassVar[ProtocolRules] = MOTEUS_RULES

    def __init__(self, bus: can.BusABC, profile: DriveProfile, *, clock: Clock = time.monotonic,
                 reset_faults: bool = False) -> None:
        super().__init__(bus, profile, clock=clock, reset_faults=reset_faults)
        require_fd_bus(bus, profile)
        opts = profile.options
        self._source = int(opts.get("source_id", 0))
        self._prefix = int(opts.get("can_prefix", 0))
        self._brs = bool(opts.get("bitrate_switch", True))
        self._query = Query.motion(resolution(profile, "position_resolution"),
                                   resolution(profile, "velocity_resolution"),
                                   resolution(profile, "torque_resolution"))
        self._rails = {reg: _MAX_CODE[res] * 1.0 for reg, res in self._query.registers.items()
                       if res is not Resolution.F32 and reg == Register.POSITION}
        self._position_step = SCALINGS[Quantity.POSITION].step(resolution(profile, "position_resolution"))
        self._command = CommandFrame(resolution=resolution(profile, "command_resolution"),
                                     timeout=profile.watchdog_timeout, query=self._query)
        self._command_id = arbitration_id(self._source, self.node_id, reply=True, prefix=self._prefix)
        self._reply_id = arbitration_id(self.node_id, self._source, reply=False, prefix=self._prefix)
        self._torque_msg = self._message(self._command.payload)
        self._keepalive = self._message(self._command.payload)
        self._stop = self._message(stop_payload(self._query))
        self._states: dict[tuple[int, int], StateEvent] = {}
        self._parser = Parser()   # the replies to one query: one shape

    # -- public ---------------------------------------------------------------

    @property
    def frame_ids(self) -> frozenset[int]:
        return frozenset({self._command_id, self._reply_id})

    @property
    def feedback_streams(self) -> bool:
        """Never: each reply answers one frame (host timing)."""
        return False

    @property
    def query(self) -> Query:
        return self._query

    @classmethod
    def preflight_probe(cls, profile: DriveProfile) -> PreflightProbe:
        from dobhil.drives.moteus.preflight import MoteusPreflight
        return MoteusPreflight(profile)

    # -- hooks ----------------------------------------------------------------

    def _message(self, data: bytes) -> can.Message:
        return can.Message(arbitration_id=self._command_id, data=bytearray(data),
                           is_extended_id=self._command_id > 0x7FF, is_fd=True, bitrate_switch=self._brs)

    def _prepare(self, deadline: float, cancel: Cancel | None) -> None:
        self._read_queued(deadline)

    def _enable_start(self) -> Sequence[can.Message]:
        return (self._stop, self._keepalive) if self._reset_faults else (self._keepalive,)

    def _enable_step(self, event: StateEvent) -> Sequence[can.Message]:
        if event.error_code in (POSITION_LOST, BAD_REPLY):
            raise DriveFaultError(f"node {self.node_id}: {event.error_text}")
        if event.state == Mode.FAULT:
            if self._reset_faults:
                return (self._stop, self._keepalive)
            raise DriveFaultError(f"node {self.node_id} is in mode FAULT with fault {event.error_text} "
                                  "(dobhil run --reset-faults sends a stop first, which clears it)")
        if event.state == Mode.TIMEOUT:
            return (self._stop, self._keepalive)   # only a stop leaves mode 11
        return ()

    def _keepalive_frames(self) -> Sequence[can.Message]:
        """A zero-torque command (kp = kd = 0): feeds the watchdog and asks for a reply."""
        self._command.fill(self._keepalive.data, 0.0)
        return (self._keepalive,)

    def _keepalive_interval(self) -> float:
        """While the enable waits: a zero-torque command every quarter of the watchdog (every
        10 ms without one), so the watchdog never expires during the handshake."""
        watchdog = self._profile.watchdog_timeout
        return watchdog / 4 if watchdog > 0 else 0.01

    def _disable_frames(self) -> Sequence[can.Message]:
        return (self._stop,)

    def _is_disabled_confirmation(self, event: StateEvent) -> bool:
        return event.state == Mode.STOPPED

    def _torque_frame(self, tau_nm: float) -> can.Message:
        self._command.fill(self._torque_msg.data, tau_nm)
        return self._torque_msg

    def _host_watch_of(self, event: StateEvent | None) -> HostTimeout | None:
        """The watchdog (register 0x027): with no command for ``watchdog_timeout`` s the
        controller enters mode 11, reported in the reply to the next frame."""
        timeout = self._profile.watchdog_timeout
        if timeout <= 0 or (event is not None and (event.state != Mode.TIMEOUT
                                                   or event.error_code in (POSITION_LOST, BAD_REPLY))):
            return None
        return HostTimeout("watchdog", timeout)

    def _fault_text(self, event: StateEvent) -> str:
        if event.error_code in (POSITION_LOST, BAD_REPLY):
            return f"node {self.node_id}: {event.error_text}"
        if event.state == Mode.FAULT:
            return f"node {self.node_id} fault: mode FAULT, fault {event.error_text}"
        if event.state == Mode.TIMEOUT:
            return (f"node {self.node_id} watchdog expired: mode TIMEOUT (no command within "
                    f"{self._profile.watchdog_timeout:g} s)")
        return f"node {self.node_id} left POSITION mode: mode {event.state_text}"

    def _enable_timeout_text(self, wait: float) -> str:
        if self._last_state is not None:
            return super()._enable_timeout_text(wait)
        return (f"no reply from node {self.node_id} on id 0x{self._reply_id:X} within {wait:g} s: check the bus "
                f"(CAN FD, 1 Mbit/s arbitration, 5 Mbit/s data), node_id {self.node_id}, moteus.can_prefix "
                f"{self._prefix} and the controller's power")

    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        if msg.arbitration_id != self._reply_id or msg.is_remote_frame or msg.is_error_frame:
            return _NO_EVENTS
        try:
            values = reply_values(bytes(msg.data), self._parser)
        except CodecError as exc:
            return (self._own_fault(BAD_REPLY, f"a reply that does not parse ({exc})"),)
        mode = values.get(Register.MODE)
        position = values.get(Register.POSITION)
        velocity = values.get(Register.VELOCITY)
        if mode is None or math.isnan(mode):
            return (self._own_fault(BAD_REPLY, "a reply without the mode register"),)
        state = self._state_event(int(mode), int(values.get(Register.FAULT, 0.0) or 0.0))
        if position is None or velocity is None:
            return (state,)
        if math.isnan(position) or self._on_rail(position):
            side = "NaN" if math.isnan(position) else f"{position:+g} rev"
            return (MotionEvent(0.0 if math.isnan(position) else position * _TAU, 0.0),
                    self._own_fault(POSITION_LOST, f"position {side}: at the end of the queried resolution's "
                                    "range or invalid; use a wider moteus.position_resolution", int(mode)))
        return (MotionEvent(position * _TAU, (0.0 if math.isnan(velocity) else velocity) * _TAU), state)

    # -- decoding -------------------------------------------------------------

    def _on_rail(self, position: float) -> bool:
        rail = self._rails.get(Register.POSITION)
        return rail is not None and abs(position) >= rail * self._position_step * (1 - 1e-9)

    def _state_event(self, mode: int, fault: int) -> StateEvent:
        """One event per (mode, fault) pair, made once (no text is formatted per cycle)."""
        key = (mode, fault)
        event = self._states.get(key)
        if event is None:
            error = fault if mode == Mode.FAULT else 0
            event = StateEvent(active=mode == Mode.POSITION, error_code=error,
                               watchdog_tripped=mode == Mode.TIMEOUT, state_text=mode_text(mode),
                               error_text=fault_text(error), state=mode)
            self._states[key] = event
        return event

    def _own_fault(self, code: int, text: str, mode: int = -1) -> StateEvent:
        """A reply the run cannot use. ``mode``: the reply's mode register where it was read
        (a position lost on its rail leaves the mode valid): a stop it says STOPPED is
        confirmed (:meth:`_is_disabled_confirmation`), not reported as a drive that may
        still be enabled."""
        return StateEvent(active=False, error_code=code, watchdog_tripped=False, state_text="reply unusable",
                          error_text=text, state=mode)
