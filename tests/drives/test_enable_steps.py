"""The Drive base's enable is a state machine stepped on what the drive reports:
``_prepare`` (start-up before any torque), the ``_enable_start`` frames, then each state
the drive reports goes through ``_enable_step`` (which answers with the next frames, or
raises to end the enable at once) until ``_is_enabled_confirmation``. A protocol without
a heartbeat period is not watched for heartbeats. Shown with a small made-up protocol on
a python-can virtual bus: the "drive" is frames queued on the other end of the bus."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence

import can
import pytest

from dobhil.drives.base import Confirmation, Drive, DriveEvent, DriveState, MotionEvent, StateEvent
from dobhil.drives.profile import DriveProfile
from dobhil.drives.waits import Cancel
from dobhil.errors import DriveError, DriveFaultError

NODE = 5
STATE_ID = 0x700 + NODE   # data[0]: the drive's state code; 3 = following torque, 9 = fault
MOTION_ID = 0x180 + NODE
START_ID, STEP_ID, TORQUE_ID, OFF_ID = 0x600 + NODE, 0x610 + NODE, 0x200 + NODE, 0x620 + NODE
_CHANNELS = itertools.count()


class SteppedDrive(Drive):
    """Answers state n with a step frame carrying n; a fault state ends the enable."""

    protocol = "stepped"

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.prepared: list[float] = []

    def _prepare(self, deadline: float, cancel: Cancel | None) -> None:
        self.prepared.append(deadline)

    def _enable_start(self) -> Sequence[can.Message]:
        return (can.Message(arbitration_id=START_ID, data=b"\x01", is_extended_id=False),)

    def _enable_step(self, event: StateEvent) -> Sequence[can.Message]:
        if event.state == 9:
            raise DriveFaultError(f"node {self.node_id} in fault (state 9); not cleared without reset_faults")
        return (can.Message(arbitration_id=STEP_ID, data=bytes([event.state]), is_extended_id=False),)

    def _disable_frames(self) -> Sequence[can.Message]:
        return (can.Message(arbitration_id=OFF_ID, data=b"\x00", is_extended_id=False),)

    def _torque_frame(self, tau_nm: float) -> can.Message:
        return can.Message(arbitration_id=TORQUE_ID, data=b"\x00\x00", is_extended_id=False)

    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        if msg.arbitration_id == STATE_ID:
            state = msg.data[0]
            return (StateEvent(state == 3, 0x1000 if state == 9 else 0, False, f"state {state}",
                               "none", state=state),)
        if msg.arbitration_id == MOTION_ID:
            return (MotionEvent(0.0, 0.0, sampled_at=12.5),)
        return ()


PROFILE = DriveProfile(protocol="stepped", firmware="1", node_id=NODE, torque_limit=1.0, velocity_limit=10.0,
                       enable_timeout=0.5)


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    channel = f"dobhil-test-steps-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    node = can.Bus(interface="virtual", channel=channel)
    yield host, node
    host.shutdown()
    node.shutdown()


def state(node: can.BusABC, code: int) -> None:
    node.send(can.Message(arbitration_id=STATE_ID, data=bytes([code]), is_extended_id=False))


def sent(node: can.BusABC) -> list[tuple[int, bytes]]:
    out = []
    while (msg := node.recv(0.0)) is not None:
        out.append((msg.arbitration_id, bytes(msg.data)))
    return out


def test_enable_prepares_starts_then_steps_on_each_state(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host, node = buses
    clock = Clock()
    drive = SteppedDrive(host, PROFILE, clock=clock)
    for code in (1, 2, 3):
        state(node, code)
    drive.enable()
    assert drive.status.state is DriveState.ENABLED
    assert drive.prepared == [100.0 + PROFILE.enable_timeout]   # the deadline covers the start-up
    frames = sent(node)
    # start frame first, then a keepalive (zero torque), then one step per reported state
    assert frames[0] == (START_ID, b"\x01")
    assert [f for f in frames if f[0] == STEP_ID] == [(STEP_ID, b"\x01"), (STEP_ID, b"\x02"), (STEP_ID, b"\x03")]
    assert (TORQUE_ID, b"\x00\x00") in frames


def test_a_step_that_raises_ends_the_enable_at_once(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host, node = buses
    drive = SteppedDrive(host, PROFILE, clock=Clock())   # the clock never moves: only the step can end it
    state(node, 1)
    state(node, 9)
    state(node, 3)   # never read: the fault ended the enable before
    with pytest.raises(DriveFaultError, match=r"^node 5 in fault \(state 9\)"):
        drive.enable()
    assert drive.status.state is DriveState.FAULT
    assert [f for f in sent(node) if f[0] == STEP_ID] == [(STEP_ID, b"\x01")]


def test_a_drive_error_from_prepare_ends_the_enable_before_any_frame(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host, node = buses

    class Refusing(SteppedDrive):
        def _prepare(self, deadline: float, cancel: Cancel | None) -> None:
            raise DriveError("node 5: SDO 0x6502 (supported drive modes) aborted: 0x06020000; state reached: "
                             "pre-operational")

    with pytest.raises(DriveError, match="0x6502"):
        Refusing(host, PROFILE, clock=Clock()).enable()
    assert sent(node) == []


def test_without_a_heartbeat_period_no_heartbeat_is_watched(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host, node = buses
    clock = Clock()
    assert PROFILE.heartbeat_period is None
    drive = SteppedDrive(host, PROFILE, clock=clock)
    state(node, 3)
    drive.enable()
    clock.now += 3600.0   # an hour without a status frame
    node.send(can.Message(arbitration_id=MOTION_ID, data=b"\x00", is_extended_id=False))
    feedback = drive.poll(0.1)
    assert drive.status.state is DriveState.ENABLED and feedback is not None
    assert feedback.sampled_at == 12.5   # carried from the MotionEvent
    # the safe stop's confirmation then waits enable_timeout (not three heartbeats)
    assert drive._confirm_timeout() == PROFILE.enable_timeout
    assert drive._keepalive_interval() > 0
    state(node, 2)
    report = drive.safe_stop()
    assert report.confirmation is Confirmation.CONFIRMED


def test_with_a_heartbeat_period_silence_is_a_fault(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """The host reads every 10 ms; the drive's status frames stop after the enable."""
    host, node = buses
    clock = Clock()
    drive = SteppedDrive(host, dataclasses.replace(PROFILE, heartbeat_period=0.1), clock=clock)
    state(node, 3)
    drive.enable()
    for _ in range(29):
        clock.now += 0.01
        drive.poll(0.0)
    clock.now += 0.021   # more than three heartbeat periods
    with pytest.raises(DriveFaultError, match=r"no heartbeat from node 5 for 0\.311 s"):
        drive.poll(0.0)


def _silent_while_away(buses: tuple[can.BusABC, can.BusABC]) -> tuple[SteppedDrive, Clock]:
    """A drive enabled, then a host that read nothing for 0.5 s (its process stopped),
    its heartbeat watch 0.3 s (three periods of 0.1 s)."""
    host, node = buses
    clock = Clock()
    drive = SteppedDrive(host, dataclasses.replace(PROFILE, heartbeat_period=0.1), clock=clock)
    state(node, 3)
    drive.enable()
    drive.poll(0.0)
    clock.now += 0.5
    return drive, clock


def test_a_silence_while_the_host_was_away_waits_for_what_is_on_its_way(
        buses: tuple[can.BusABC, can.BusABC]) -> None:
    """Back after 0.5 s, the host has read no status frame for 0.5 s: the frames the drive
    sent meanwhile may still be on their way (a hub forwards them late), so no fault yet;
    the state they bring (a fault of the drive's: what stopped it) is what the host reports."""
    drive, clock = _silent_while_away(buses)
    _host, node = buses
    assert drive.poll(0.0) is None and drive.status.state is DriveState.ENABLED
    clock.now += 0.02
    state(node, 9)   # late: the drive faulted while the host was away
    with pytest.raises(DriveFaultError, match="state 9"):
        drive.poll(0.0)


def test_a_silence_lasting_the_watch_after_the_host_is_back_is_the_drives(
        buses: tuple[can.BusABC, can.BusABC]) -> None:
    drive, clock = _silent_while_away(buses)
    back = clock.now
    for i in range(30):   # 0.29 s of reading from the host's return: still the watch
        clock.now = back + i * 0.01
        drive.poll(0.0)
    assert drive.status.state is DriveState.ENABLED
    clock.now = back + 0.301
    with pytest.raises(DriveFaultError, match=r"no heartbeat from node 5 for 0\.801 s"):
        drive.poll(0.0)


def test_a_heartbeat_after_the_host_is_back_ends_the_silence(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """A heartbeat read after the return ends the silence: the next one, host away
    again, is judged from scratch (the watch again from the next return)."""
    drive, clock = _silent_while_away(buses)
    _host, node = buses
    drive.poll(0.0)
    clock.now += 0.05
    state(node, 3)
    drive.poll(0.0)
    clock.now += 0.5   # away again, from the heartbeat
    drive.poll(0.0)
    clock.now += 0.2
    assert drive.poll(0.0) is None and drive.status.state is DriveState.ENABLED
    clock.now += 0.11
    with pytest.raises(DriveFaultError, match="no heartbeat from node 5"):
        drive.poll(0.0)


def test_defaults_of_the_new_fields_and_hooks(buses: tuple[can.BusABC, can.BusABC]) -> None:
    host, _node = buses
    assert StateEvent(True, 0, False, "x", "none").state == -1
    drive = SteppedDrive(host, PROFILE)
    assert drive.feedback_streams is True and drive._reset_faults is False
    assert SteppedDrive(host, PROFILE, reset_faults=True)._reset_faults is True
    assert Drive._enable_step(drive, StateEvent(True, 0, False, "x", "none")) == ()


def test_a_drive_that_does_not_stream_refuses_feedback_timing(buses: tuple[can.BusABC, can.BusABC]) -> None:
    from dobhil.errors import ConfigError
    from dobhil.runtime.loop import Timing
    from dobhil.runtime.session import check_feedback_streams

    class Asked(SteppedDrive):
        @property
        def feedback_streams(self) -> bool:
            return False

    host, _node = buses
    drive = Asked(host, PROFILE)
    with pytest.raises(ConfigError, match=r"^loop.timing = feedback .* node 5 \(stepped\) .*; set loop.timing: host$"):
        check_feedback_streams(Timing.FEEDBACK, drive)
    for timing in (Timing.HOST, Timing.LOCKSTEP):
        check_feedback_streams(timing, drive)
    check_feedback_streams(Timing.FEEDBACK, SteppedDrive(host, PROFILE))


class BlindDrive(SteppedDrive):
    """The same protocol, but its frames cannot confirm the disable (as MIT on a CubeMars)."""

    @property
    def confirms_disable(self) -> bool:
        return False


def test_a_drive_that_cannot_confirm_its_disable_is_never_reported_safe(
        buses: tuple[can.BusABC, can.BusABC]) -> None:
    """No answer after the safe-stop frames: NOT_ACKNOWLEDGED, loud -- and a status frame
    queued before them answers none of them (it is read first, not taken for the answer)."""
    host, node = buses
    assert SteppedDrive(host, PROFILE).confirms_disable is True   # the default: ODrive, CiA 402
    drive = BlindDrive(host, PROFILE, clock=Clock())
    state(node, 3)
    drive.enable()
    state(node, 2)   # before the safe stop: no answer to it
    report = drive.safe_stop(timeout=0.0, planned=True)
    assert [f.what for f in report.frames] == ["zero torque", "disable"] and report.sent
    assert report.confirmation is Confirmation.NOT_ACKNOWLEDGED and not report.safe and report.note() == ""
    assert report.warning() == ("drive may still be enabled: node 5 did not answer disable (no answer within 0 s); "
                                "cut power")
    assert drive.status.state is DriveState.DISABLED and "disable of node 5 failed" in drive.status.detail
    # without a confirmation asked (disable()), or a drive never heard from, nothing changes
    assert BlindDrive(host, PROFILE).safe_stop(confirm=False).confirmation is Confirmation.NOT_ASKED
    assert BlindDrive(host, PROFILE).safe_stop().confirmation is Confirmation.NEVER_SEEN


@pytest.mark.parametrize("blind", [False, True], ids=["confirms", "cannot-confirm"])
def test_a_drive_sent_its_enable_frames_but_never_heard_is_not_safe(
        buses: tuple[can.BusABC, can.BusABC], blind: bool) -> None:
    """Nothing is ever heard from the drive: before its enable frames went out, it was never
    enabled by us (NEVER_SEEN, safe); once they went out, it may have taken them silently,
    and nothing can confirm its disable (NEVER_ANSWERED, the loud line, at a planned end
    too), whatever the protocol can confirm."""
    host, node = buses
    kind = BlindDrive if blind else SteppedDrive
    assert kind(host, PROFILE).safe_stop().confirmation is Confirmation.NEVER_SEEN
    drive = kind(host, PROFILE)
    with pytest.raises(DriveError, match="no heartbeat from node 5 within 0.01 s"):
        drive.enable(timeout=0.01)
    sent = iter(lambda: node.recv(0.1), None)
    assert START_ID in {msg.arbitration_id for msg in sent}   # the enable frame went out
    report = drive.safe_stop(timeout=0.0, planned=True)
    assert report.sent and report.confirmation is Confirmation.NEVER_ANSWERED
    assert not report.safe and report.note() == ""
    assert report.warning() == ("drive may still be enabled: node 5 never answered: its enable frames (for enabled) "
                                "went out and nothing was heard from it since, so disable cannot be confirmed; "
                                "cut power")
    assert drive.status.state is DriveState.DISABLED and "disable of node 5 failed" in drive.status.detail


class Answering(can.Listener):
    """The made-up drive's end of the bus: a status frame in answer to the disable frame."""

    def __init__(self, node: can.BusABC) -> None:
        self.node = node

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == OFF_ID:
            state(self.node, 2)


def test_a_drive_first_heard_during_the_safe_stop_confirms_it(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """A drive silent until after its enable timed out (just powered, its emulator still
    starting) that answers the disable frame within the wait: its answer confirms the
    disable, as any drive's does -- NEVER_ANSWERED is for one silent to the end."""
    host, node = buses
    drive = SteppedDrive(host, PROFILE)
    with pytest.raises(DriveError, match="no heartbeat from node 5"):
        drive.enable(timeout=0.01)
    while node.recv(0.0) is not None:   # the enable frames, unanswered
        pass
    notifier = can.Notifier(node, [Answering(node)], timeout=0.01)   # stop() joins within 0.01 s, not 1 s
    try:
        report = drive.safe_stop(timeout=2.0)
    finally:
        notifier.stop()
    assert report.sent and report.confirmation is Confirmation.CONFIRMED and report.safe, report


@pytest.mark.parametrize("planned", [True, False], ids=["planned-end", "fault-timeout-or-signal"])
def test_an_answered_unconfirmable_disable_is_a_note_only_at_a_planned_end(
        buses: tuple[can.BusABC, can.BusABC], planned: bool) -> None:
    """The drive answered the disable, but its frames cannot say it left torque control: a
    note (what was confirmed, and why no more) when the run lasted its duration, the loud
    line with the same account at any other end."""
    host, node = buses
    drive = BlindDrive(host, PROFILE)
    state(node, 3)
    drive.enable()
    notifier = can.Notifier(node, [Answering(node)], timeout=0.01)
    try:
        report = drive.safe_stop(timeout=2.0, planned=planned)
    finally:
        notifier.stop()
    assert report.confirmation is Confirmation.UNCONFIRMABLE and not report.safe and report.planned is planned
    account = ("disable sent and node 5 answered, but protocol 'stepped' cannot confirm it: its frames carry "
               "no drive state")
    assert report.detail == account
    if planned:
        assert report.warning() == "" and report.note() == f"node 5 cannot confirm its disable by design: {account}"
    else:
        assert report.note() == "" and report.warning() == f"drive may still be enabled: node 5 {account}; cut power"
    assert drive.status.state is DriveState.DISABLED and "disable of node 5 cannot be confirmed" in drive.status.detail


def test_since_back_is_the_host_s_return_from_its_last_gap_that_long(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """``since_back(gap)``: how long ago the host came back from its latest gap of ``gap``
    s or longer between reads, since the last fresh motion frame (inf: none)."""
    host, node = buses
    clock = Clock()
    drive = SteppedDrive(host, PROFILE, clock=clock)
    state(node, 3)
    drive.enable()
    assert drive.since_back(0.0) == math.inf   # nothing read since the enable
    clock.now += 0.5   # away
    drive.poll(0.0)
    clock.now += 0.01
    drive.poll(0.0)
    clock.now += 0.2   # away again, shorter
    drive.poll(0.0)
    clock.now += 0.03
    assert math.isclose(drive.since_back(0.4), 0.24) and math.isclose(drive.since_back(0.1), 0.03)
    assert math.isclose(drive.since_back(0.01), 0.03) and drive.since_back(0.6) == math.inf
    node.send(can.Message(arbitration_id=MOTION_ID, data=b"\x00", is_extended_id=False))
    assert drive.poll(0.0) is not None   # fresh feedback: the gaps before it no longer count
    assert drive.since_back(0.0) == math.inf
