"""Lockstep on a drive whose feedback does not stream (``Drive.feedback_streams`` False):
the loop runs the host algorithm on simulated time (``ForceLoop._run_lockstep_requests``).

The drive here is a minimal request/reply drive of the test's own on the emulated MIT
motor (enter, pure-torque commands, replies decoded by the codec), so this checks the
loop's timing independently of the MIT drive: every cycle at exactly ``t0 + k T``, its
feedback the reply to the previous command (the state at ``t_{k-1}``), its torque acting
from ``t_k`` to ``t_{k+1}`` (one whole period of delay, as ``command_delay_periods: 1``
makes the analysis model it), and the force loop converging on it. ODrive and CiA 402
lockstep keep their feedback-synchronous path (their own tests cover it unchanged)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import can
import pytest

from dobhil.drives.base import Drive, DriveEvent, Feedback, MotionEvent, StateEvent
from dobhil.drives.mit.codec import Command, Special, pack_command, special_frame, unpack_reply
from dobhil.drives.profile import DriveProfile
from dobhil.drives.mit.emulator import EmulatedMit, model_of
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus
from dobhil.drives.emulated import private_virtual_channel
from dobhil.runtime.controller import ControlOutput
from dobhil.runtime.loop import ForceLoop, Timing
from dobhil.runtime.references import make_reference
from dobhil.runtime.session import build_controller, loop_settings
from dobhil.runtime.stop import Stop, StopReason

from .helpers import REPO, STEP_FROM_ZERO, demo_config
from tests.emulator.mit_rig import DAMIAO, mit_profile

T = 1e-3


class _RequestDrive(Drive):
    """Enter, pure torque, exit; replies decoded by the codec (a Damiao: its state nibble
    says motor mode, so the safe stop is confirmed)."""

    protocol = "mit-test"

    def __init__(self, bus: can.BusABC, profile: DriveProfile, **kwargs: Any) -> None:
        super().__init__(bus, profile, **kwargs)
        self.model = model_of(profile)

    @property
    def feedback_streams(self) -> bool:
        return False

    def _frame(self, data: bytes) -> can.Message:
        return can.Message(arbitration_id=self.node_id, is_extended_id=False, data=data)

    def _enable_start(self) -> Sequence[can.Message]:
        return (self._frame(special_frame(Special.ENTER)),)

    def _disable_frames(self) -> Sequence[can.Message]:
        return (self._frame(special_frame(Special.EXIT)),)

    def _torque_frame(self, tau_nm: float) -> can.Message:
        return self._frame(pack_command(self.model, Command(0.0, 0.0, 0.0, 0.0, tau_nm)))

    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        if msg.arbitration_id != 0 or len(msg.data) != 8:
            return ()
        reply = unpack_reply(self.model, bytes(msg.data))
        return (MotionEvent(reply.position, reply.velocity),
                StateEvent(reply.state != 0, reply.error if reply.error > 0 else 0, False,
                           "rest" if reply.state == 0 else "motor", reply.error_text))


class _Log(EmulatedMit):
    """The emulated motor, logging each reply: (emulator time, data)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.sent: list[tuple[float, bytes]] = []

    def _send(self, msg: can.Message) -> None:
        self.sent.append((self._time, bytes(msg.data)))
        super()._send(msg)


class _Sink:
    def __init__(self, clock: Any) -> None:
        self.clock = clock
        self.rows: list[tuple[int, float, float, Feedback, float]] = []

    def started(self, fb: Feedback) -> None:
        self.t0 = self.clock()

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        self.rows.append((k, t, self.clock(), fb, out.u))

    def stop(self, stop: Stop) -> None:
        pass


def _run(duration: float) -> tuple[Any, _Log, _Sink, Plant]:
    config = demo_config("design.delay_samples=1", "design.input_delay=0", "design.dob_bandwidth=250",
                         "design.rtob_bandwidth=250", *STEP_FROM_ZERO)
    profile = mit_profile(DAMIAO, node_id=3)
    plant = Plant.from_config(config)
    channel = private_virtual_channel()
    host, emu_bus = can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)
    emulator = _Log(emu_bus, profile, plant)
    lock = LockstepBus(host, [emulator], dt=T)
    try:
        drive = _RequestDrive(lock, profile, clock=lock.clock)
        sink = _Sink(lock.clock)
        loop = ForceLoop(drive=drive, controller=build_controller(config, profile),
                         reference=make_reference(config.reference, None, duration=duration),
                         settings=loop_settings(config, Timing.LOCKSTEP, duration, profile), clock=lock.clock,
                         truth=lambda: (plant.interaction_torque, plant.true_position), sink=sink)
        result = loop.run()
    finally:
        lock.shutdown()
        emulator.close()
        host.shutdown()
    return result, emulator, sink, plant


def test_cycles_run_on_simulated_deadlines_with_one_period_of_delay() -> None:
    result, emulator, sink, _ = _run(0.05)
    assert result.stop.reason is StopReason.DONE and result.cycles == 50 and result.disabled
    model = emulator.model
    t0 = sink.t0
    replies: dict[int, bytes] = {}
    for at, data in emulator.sent:   # the first reply at each instant: the cycle's command's
        if at >= t0 - 1e-12:
            replies.setdefault(round((at - t0) / T), data)
    quantum = model.quanta.torque
    for k, t, now, fb, _u in sink.rows:
        assert t == pytest.approx(k * T, abs=1e-12) and now - t0 == pytest.approx(k * T, abs=1e-9)
        if k == 0:
            continue
        # the feedback of cycle k is the reply sent at t_{k-1}: the state one period old
        assert (fb.position, fb.velocity) == _motion(model, replies[k - 1])
        # the reply at t_k carries the torque applied up to t_k: cycle k-1's command
        prev_u = sink.rows[k - 1][4]
        assert abs(unpack_reply(model, replies[k]).torque - prev_u) <= quantum
    assert [row[3].seq for row in sink.rows] == sorted({row[3].seq for row in sink.rows})   # all fresh
    # the last command acts for its whole period, as in host timing: the run ends at t_n, the
    # reply there (to the safe stop's first frame) carries the torque of cycle n-1
    assert result.stop.time == pytest.approx(50 * T, abs=1e-9)
    assert abs(unpack_reply(model, replies[50]).torque - sink.rows[-1][4]) <= quantum


def _motion(model: Any, data: bytes) -> tuple[float, float]:
    reply = unpack_reply(model, data)
    return reply.position, reply.velocity


def test_the_force_loop_converges_on_it() -> None:
    result, _, _, plant = _run(0.6)
    assert result.stop.reason is StopReason.DONE
    tau = result.trace["tau_int_true"]
    tail = tau[-100:]
    # a 1 N m step from t = 0 (STEP_FROM_ZERO); quantisation leaves a small ripple
    assert abs(float(tail.mean()) - 1.0) < 0.02 and float(tail.std()) < 0.05
    assert math.isfinite(plant.interaction_torque)


def test_a_silent_motor_stops_the_run_on_the_simulated_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    """Replies stop (the motor set to zero: silent): no fresh feedback for
    loop.feedback_timeout of simulated time ends the run."""
    calls = {"n": 0}
    original = EmulatedMit._reply

    def reply(self: EmulatedMit, torque: float) -> None:
        calls["n"] += 1
        if calls["n"] <= 20:
            original(self, torque)

    monkeypatch.setattr(EmulatedMit, "_reply", reply)
    result, emulator, sink, _ = _run(0.2)
    assert result.stop.reason is StopReason.FEEDBACK_TIMEOUT and "simulated" in result.stop.detail
    assert 10 < result.cycles < 40


def test_an_overheated_motor_stops_the_run_with_its_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """configs/mit-demo.yaml in lockstep with the MIT drive, the emulated AK80-9's winding
    made to overheat at the demo's torques (a steady rise of 250 K at 0.5 N m, time
    constant 50 ms): the reply's error byte 1 reaches the drive, the run stops as
    drive_fault naming over temperature, and the safe stop still goes out."""
    from dobhil.config import load_config
    from dobhil.drives.mit.emulator import Thermal
    from dobhil.runtime.session import RunSession

    hot = Thermal(rise_at_t_max=250.0 * (18.0 / 0.5) ** 2, time_constant=0.05)
    original = EmulatedMit.__init__

    def init(self: EmulatedMit, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **{**kwargs, "thermal": hot})

    monkeypatch.setattr(EmulatedMit, "__init__", init)
    config = load_config(REPO / "configs" / "mit-demo.yaml")
    with RunSession(config, emulate=True, lockstep=True) as session:
        result = session.run()
        emulator = session.emulator
    assert result.stop.reason is StopReason.DRIVE_FAULT, result.stop.line()
    assert "over temperature" in result.stop.detail
    assert isinstance(emulator, EmulatedMit) and emulator.protocol_error == 1 and emulator.protocol_state == 0
    assert result.safe_stop is not None and result.safe_stop.sent
    # 0.2 N m heats to 65 degC at most: the fault comes after the step to 1 N m at 0.6 s
    assert 0.6 < result.stop.time < 1.2
