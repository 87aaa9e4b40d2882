"""The drive boundary: public methods here, protocol hooks in each subclass.

Like python-can's ``BusABC.recv()`` / ``_recv_internal()``: :class:`Drive` owns timeouts,
state and safety (enable handshake wait, fault detection, a ``disable()`` that never
raises); a protocol module fills in :meth:`Drive._enable_start`,
:meth:`Drive._disable_frames`, :meth:`Drive._torque_frame`, :meth:`Drive._decode` and
optionally :meth:`Drive._prepare`, :meth:`Drive._enable_step` and
:meth:`Drive._is_enabled_confirmation`, and says how its profiles are validated
(:attr:`Drive.profile_rules`).

Enabling is a state machine stepped on what the drive reports: ``_prepare`` (start-up
before any torque, e.g. CiA 402's NMT and SDO set-up), the ``_enable_start`` frames, then
each :class:`StateEvent` goes through ``_enable_step``, which answers with the next
frames (a CiA 402 controlword per power state) or raises to end the enable at once,
until ``_is_enabled_confirmation`` says the drive follows torque commands.

Protocol modules report what they decode as protocol-neutral events:
:class:`MotionEvent` (position/velocity in rad, rad/s) and :class:`StateEvent`
(whether the drive follows torque commands, its error code, and text for messages).

Host timeouts: a drive that watches the host (an ODrive's watchdog on its setpoints, a CiA
402 node's heartbeat consumer, an MIT motor's command timeout) faults when the host's frames
stop coming, whoever stopped them. :attr:`Drive.host_watch` says what the drive watches and
how long it waits (:class:`HostTimeout`), :meth:`Drive.host_timeout` whether the fault it
reports now is that watch expiring; each protocol classifies its own faults
(:meth:`Drive._host_watch_of`). The loop compares it with what it measured of its own
lateness: a fault that followed a host too late to feed the watch is the host's.

Hot path (``send_torque``, ``poll``): no logging, no printing, no blocking beyond the
given timeout; the torque frame may be a preallocated message the hook refills.

Safe stop (:meth:`Drive.safe_stop`): every frame of it -- zero torque, then each disable
frame -- is attempted on its own, whatever happened to the one before (a bus that
refuses one frame may take the next), each with its own :class:`FrameResult`; then the
drive's own status frames must confirm that it left torque control. What was sent and
what was confirmed comes back as a :class:`SafeStopReport`, whose
:meth:`~SafeStopReport.warning` is the one loud line a user must see when the drive may
still be enabled. A protocol whose frames cannot say that the drive left torque control
(MIT mode on a CubeMars AK: its replies carry no mode) sets :attr:`Drive.confirms_disable`
False: its safe stop then waits for the drive's answer to the safe-stop frames and asks
the hook :meth:`Drive._disable_answer` what that answer shows (MIT: the reply to the exit
frame arrived, with zero torque in it). An answer is :attr:`Confirmation.UNCONFIRMABLE`,
never "safe": at a planned end of a run (``safe_stop(planned=True)``) its account is a
note (:meth:`SafeStopReport.note`), at any other end (a fault, a timeout, a signal) the
loud line; no answer at all is :attr:`Confirmation.NOT_ACKNOWLEDGED`, loud always.
Whatever the protocol, a drive never heard from is safe only if it was never sent its enable
frames (:attr:`Confirmation.NEVER_SEEN`); once they went out it may have taken them
silently, and the stop is :attr:`Confirmation.NEVER_ANSWERED`, loud always.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import IntEnum
from functools import partial
from typing import TYPE_CHECKING, ClassVar

import can

from dobhil.drives.profile import DriveProfile, ProtocolRules
from dobhil.drives.waits import Cancel, sliced_frames
from dobhil.errors import BusError, ConfigError, DriveError, DriveFaultError, DriveTimeoutError, WaitCancelled
from dobhil.errors import exception_line

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = [
    "Confirmation",
    "Drive",
    "DriveEvent",
    "DriveState",
    "DriveStatus",
    "Feedback",
    "FrameResult",
    "HostTimeout",
    "MotionEvent",
    "SafeStopReport",
    "StateEvent",
]

Clock = Callable[[], float]


#: heartbeats a drive may miss in a row before the host calls it a fault
HEARTBEAT_MISSES = 3
#: wall-clock seconds a safe-stop frame is retried while the bus refuses it (ENOBUFS:
#: a full transmit queue drains within a few frame times)
SAFE_STOP_RETRY = 0.02
#: attempts a refused safe-stop frame gets at least, however long they take: a host the
#: machine did not run for the whole SAFE_STOP_RETRY window would else give up after one
#: retry, just when the queue has had time to drain
SAFE_STOP_ATTEMPTS = 3
#: keepalive interval of enable() when neither a watchdog nor a heartbeat period sets
#: one: often enough to ask a drive for status, seldom enough to load no bus
DEFAULT_KEEPALIVE = 0.1
#: seconds between the status requests of a safe stop's confirmation wait
#: (:meth:`Drive._status_request_frames`): a drive that takes a few ms to leave torque control
#: answers the first request still in it, and the next one confirms
STATUS_REQUEST_INTERVAL = 0.01
#: frames a safe stop reads off the bus before its frames at most (a drive that cannot
#: confirm its disable: what was queued answers none of them); a flooded bus cannot hold it
DRAIN_LIMIT = 1000


class DriveState(IntEnum):
    DISABLED = 0
    ENABLED = 1
    FAULT = 2


@dataclass(frozen=True, slots=True)
class Feedback:
    """Newest motion sample. ``timestamp``: drive clock [s] when the frame was read;
    ``rx_time``: the bus's receive stamp of the frame (python-can ``Message.timestamp``,
    ``time.time()`` seconds; NaN if the bus gave none); ``sampled_at``: the bus stamp (same
    clock as ``rx_time``) of the instant the drive sampled it (CiA 402: the SYNC's), NaN
    when the protocol does not tell (ODrive)."""

    timestamp: float
    position: float  # rad
    velocity: float  # rad/s
    seq: int  # counts motion frames received from this drive
    rx_time: float = math.nan
    sampled_at: float = math.nan

    @property
    def sample_latency(self) -> float:
        """The drive's sample instant -> this feedback received [s], both bus stamps
        (NaN when either is unknown): what the sample is old when the host reads it."""
        return self.rx_time - self.sampled_at


@dataclass(frozen=True, slots=True)
class DriveStatus:
    """What the host knows of the drive: dobhil's :class:`DriveState`, and the drive's own
    codes as its protocol reports them (``protocol_state``: -1 before any state frame or
    for a protocol without one; ``error_code``: 0 none); the protocol object names both
    (:meth:`dobhil.drives.plugin.DriveProtocol.state_name`, ``error_text``)."""

    state: DriveState
    error_code: int = 0
    watchdog_tripped: bool = False  # the watchdog expired while the drive was enabled (since its enable)
    last_heartbeat: float | None = None  # drive clock [s]
    detail: str = ""  # last fault / enable / disable-failure text, one line
    protocol_state: int = -1  # the drive's own state code (StateEvent.state)


class Confirmation(IntEnum):
    """What the drive said after the safe-stop frames."""

    CONFIRMED = 0         # a status frame after the disable frames: out of torque control
    NOT_ACKNOWLEDGED = 1  # frames sent, but no status frame confirmed it in time
    NOT_SENT = 2          # a safe-stop frame could not be put on the bus
    #: nothing was ever heard from the drive and it was never sent its enable frames:
    #: this host never enabled it, nothing to confirm
    NEVER_SEEN = 3
    NOT_ASKED = 4         # sent without waiting for a confirmation (``disable()``)
    #: the protocol's frames cannot say that the drive left torque control (MIT mode on a
    #: CubeMars AK: its replies carry no mode), but the drive answered the safe-stop frames
    #: and the answer showed what the protocol can show (the report's detail): never safe;
    #: a note at a planned end, the loud line at any other
    UNCONFIRMABLE = 5
    #: the drive was sent its enable frames but nothing was ever heard from it: a drive
    #: that took them silently (its replies lost, a wrong reply id, a heartbeat switched
    #: off) may be enabled, and nothing it sends can confirm the disable: loud always
    NEVER_ANSWERED = 6


@dataclass(frozen=True, slots=True)
class FrameResult:
    """One safe-stop frame: what it was, whether it went out, why not, and how many of its
    attempts the bus refused (retried for :data:`SAFE_STOP_RETRY` s and at least
    :data:`SAFE_STOP_ATTEMPTS` times: a full transmit queue that drains meanwhile takes it)."""

    what: str   # e.g. "zero torque", "IDLE"
    sent: bool
    error: str = ""
    refused: int = 0   # attempts the bus refused (all of them when not sent)


@dataclass(frozen=True, slots=True)
class SafeStopReport:
    """Every safe-stop frame's result and what the drive confirmed."""

    node_id: int
    frames: tuple[FrameResult, ...]
    confirmation: Confirmation
    detail: str = ""  # one line: why it is not confirmed (empty when it is)
    #: the stop was the run's planned end (it lasted its duration), not a fault, a
    #: timeout or a signal: what a drive that cannot confirm by design did confirm is then
    #: a note, not the loud line
    planned: bool = False

    @property
    def sent(self) -> bool:
        """Every safe-stop frame went out."""
        return all(f.sent for f in self.frames)

    @property
    def safe(self) -> bool:
        """Known to be out of torque control (or never heard of and never sent its enable
        frames: never enabled by us)."""
        return self.sent and self.confirmation in (Confirmation.CONFIRMED,
                                                   Confirmation.NEVER_SEEN,
                                                   Confirmation.NOT_ASKED)

    @property
    def noted(self) -> bool:
        """Not confirmable by design, but every frame went out, the drive answered them
        and the stop was planned: a note, not a warning."""
        return self.sent and self.planned and self.confirmation is Confirmation.UNCONFIRMABLE

    def warning(self) -> str:
        """The one loud line when the drive may still be enabled; empty when safe (or
        :attr:`noted`)."""
        if self.safe or self.noted:
            return ""
        return f"drive may still be enabled: node {self.node_id} {self.detail}; cut power"

    def note(self) -> str:
        """The one line that says what a drive which cannot confirm its disable by design
        did confirm, at a planned end; empty otherwise (then :meth:`warning` speaks)."""
        if not self.noted:
            return ""
        return f"node {self.node_id} cannot confirm its disable by design: {self.detail}"


@dataclass(frozen=True, slots=True)
class MotionEvent:
    position: float  # rad
    velocity: float  # rad/s
    sampled_at: float = math.nan  # bus stamp of the sampling instant (CiA 402: the SYNC's); NaN: unknown


@dataclass(frozen=True, slots=True)
class StateEvent:
    active: bool  # the drive follows torque commands (e.g. ODrive CLOSED_LOOP_CONTROL)
    error_code: int
    watchdog_tripped: bool
    state_text: str  # e.g. "IDLE"
    error_text: str  # e.g. "0x01000000 (WATCHDOG_TIMER_EXPIRED)"
    state: int = -1  # the drive's own state code (ODrive axis state, CiA 402 statusword); -1: none


DriveEvent = MotionEvent | StateEvent


@dataclass(frozen=True, slots=True)
class HostTimeout:
    """A drive's watch on the host's frames: the drive faults when they stop for
    ``timeout`` s. ``fed_every``: how often the host's frame that feeds it goes out at
    least, beside the torque commands (a host heartbeat every 25 ms: a command gap of
    ``timeout - fed_every`` already starves the watch; 0 when the commands feed it);
    ``reported_within``: how long after it fires the host hears of it at the latest (an
    ODrive's heartbeat period: its status rides on the heartbeat)."""

    what: str               # the drive's name for it, in messages ("watchdog")
    timeout: float          # [s]
    fed_every: float = 0.0  # [s]
    reported_within: float = 0.0  # [s]

    @property
    def starving_gap(self) -> float:
        """[s] the shortest gap between the host's commands that can starve the watch."""
        return max(self.timeout - self.fed_every, 0.0)


_NO_EVENTS: tuple[DriveEvent, ...] = ()


class Drive(ABC):
    """One servo drive on a python-can bus, commanded in torque [Nm].

    The bus is borrowed, not owned: the caller shuts it down. ``clock`` is the time
    source of timeouts and timestamps (``time.monotonic`` by default; a lockstep
    emulator passes its simulated clock).
    """

    protocol: ClassVar[str] = ""
    active_state_text: ClassVar[str] = "enabled"
    #: what the disable frames ask for, in messages ("IDLE" on an ODrive)
    disabled_state_text: ClassVar[str] = "disable"
    #: how this protocol's profiles are validated: its section, narrower common keys and
    #: the optional common keys it needs (read by :mod:`dobhil.drives.profile` through the
    #: registry when a profile is loaded)
    profile_rules: ClassVar[ProtocolRules] = ProtocolRules()

    def __init__(
        self, bus: can.BusABC, profile: DriveProfile, *, clock: Clock = time.monotonic,
        reset_faults: bool = False,
    ) -> None:
        """``reset_faults``: the enable may clear a drive fault first (``dobhil run
        --reset-faults``); off, a faulted drive refuses to enable (protocols that clear
        errors as part of their enable, like ODrive's Clear_Errors, are not affected)."""
        for key in sorted(self.profile_rules.requires):
            # a profile read from YAML was refused already; one built in code is caught here
            if getattr(profile, key) is None:
                raise ConfigError(f"drive profile {profile.name or profile.protocol!r}: missing key "
                                  f"{key!r} (protocol {self.protocol!r} needs it)")
        self._bus = bus
        self._reset_faults = reset_faults
        self._profile = profile
        self._clock = clock
        self._state = DriveState.DISABLED
        self._feedback: Feedback | None = None
        self._seq = 0
        self._last_state: StateEvent | None = None
        self._last_heartbeat: float | None = None
        #: (drive clock) when the host last finished reading the bus: :meth:`poll`'s end,
        #: or the enable; ``_unread``: from the one before to it
        self._read_at = -math.inf
        self._unread = 0.0
        #: the host's gaps between reads since the last fresh motion frame, as (gap [s], its
        #: end on the drive clock), each longer than every later one (:meth:`since_back`)
        self._gaps: list[tuple[float, float]] = []
        #: (drive clock) the first read after the host was away longer than the watch,
        #: during a heartbeat silence; None when there is no such silence
        self._back_at: float | None = None
        self._detail = ""
        self._fault_event: StateEvent | None = None   # the state that faulted the drive
        #: the drive's watchdog expired while it was enabled (since the last enable): what
        #: DriveStatus.watchdog_tripped says. Not the last state frame's flag: a drive's
        #: watchdog also runs disabled (an ODrive checks it in every axis state), so the
        #: frame confirming a safe stop may carry the bit of an axis nobody feeds any more
        self._watchdog_expired = False
        self._status_cache: DriveStatus | None = None
        #: the enable frames were handed to the bus at least once: from then on a drive
        #: never heard from may have enabled (its safe stop cannot call it NEVER_SEEN)
        self._enable_sent = False
        #: what the last start-up (``_prepare``) could not check on the drive, one line
        #: each (nothing was refused for them); ``dobhil run`` prints them
        self.notes: list[str] = []

    # -- public API -----------------------------------------------------------

    @property
    def profile(self) -> DriveProfile:
        return self._profile

    @property
    def node_id(self) -> int:
        return self._profile.node_id

    @property
    def frame_ids(self) -> frozenset[int] | None:
        """Arbitration ids of this drive's frames (None: not known), e.g. for a recorder to
        tell them from foreign traffic."""
        return None

    @property
    def feedback_streams(self) -> bool:
        """True when the drive sends motion feedback on its own every period; False when
        it only answers the host each cycle (CiA 402 without a native periodic SYNC): a
        loop timed by feedback cannot run on it."""
        return True

    @property
    def sample_clock(self) -> str:
        """What :attr:`Feedback.sampled_at` is stamped with: "" when the protocol does not
        tell its sample instant (NaN), "bus" when it is the bus's receive stamp of the frame
        the drive sampled at (the clock of ``rx_time``), "sent" when it is this host's wall
        clock just after it sent that frame. A run's log records it (``run.sample_clock``),
        so that its report can say which clock the sample latency is on."""
        return ""

    @property
    def feedback(self) -> Feedback | None:
        """Newest feedback seen so far (fresh or not)."""
        return self._feedback

    @property
    def status(self) -> DriveStatus:
        if self._status_cache is None:
            last = self._last_state
            self._status_cache = DriveStatus(
                state=self._state,
                error_code=last.error_code if last else 0,
                watchdog_tripped=self._watchdog_expired,
                last_heartbeat=self._last_heartbeat,
                detail=self._detail,
                protocol_state=last.state if last else -1,
            )
        return self._status_cache

    @property
    def host_watch(self) -> HostTimeout | None:
        """The drive's watch on the host's commands as this drive was set up (its
        watchdog, heartbeat consumer or command timeout), or None: none that a late host
        can trip (none configured, or fed by something the host's process does not send)."""
        return self._host_watch_of(None)

    def host_timeout(self) -> HostTimeout | None:
        """While the drive is faulted because its watch on the host's frames expired
        (:attr:`host_watch`): that watch; None for any other state or fault (the drive's
        own). Never raises."""
        event = self._fault_event
        if self._state is not DriveState.FAULT or event is None:
            return None
        try:
            return self._host_watch_of(event)
        except Exception:  # a classification that fails blames the drive, as before
            return None

    def enable(self, timeout: float | None = None, *, cancel: Cancel | None = None) -> None:
        """Run the enable handshake and wait for the drive to confirm it.

        Raises DriveTimeoutError naming what was awaited and what was last seen,
        BusError if the frames cannot be sent or the bus cannot be read, WaitCancelled
        within WAIT_SLICE s of ``cancel()`` returning a reason, DriveError /
        DriveFaultError from the protocol's start-up or enable steps (one line).
        """
        wait = self._profile.enable_timeout if timeout is None else timeout
        deadline = self._clock() + wait
        self._set_state(DriveState.DISABLED, "")
        self._last_state = None
        self._watchdog_expired = False
        self._prepare(deadline, cancel)
        # set before the send: a send that fails part-way may have put a frame on the bus
        self._enable_sent = True
        self._send_all(self._enable_start(), "enable")
        if self._await_enabled(deadline, cancel):
            self._set_state(DriveState.ENABLED, "")
            self._read_at, self._unread, self._back_at = self._clock(), 0.0, None
            self._gaps.clear()
            return
        raise DriveTimeoutError(self._enable_timeout_text(wait))

    def disable(self) -> bool:
        """Zero torque, then the protocol's disable frames, without waiting for a
        confirmation. Never raises. True if every frame was sent; otherwise the failure
        is in ``status.detail`` and the host side is marked DISABLED anyway."""
        return self.safe_stop(confirm=False).sent

    def safe_stop(self, *, confirm: bool = True, timeout: float | None = None,
                  cancel: Cancel | None = None, planned: bool = False) -> SafeStopReport:
        """Zero torque, then each disable frame -- every one attempted, whatever happened
        to the others -- then (``confirm``) wait up to ``timeout`` s (default: three
        heartbeat periods) for a status frame saying the drive left torque control (a
        drive that cannot say so: for its answer, :meth:`_disable_answer`); a reason from
        ``cancel()`` ends that wait within WAIT_SLICE s, unconfirmed. ``planned``: the
        run lasted its duration (recorded in the report: it decides note or warning).
        Never raises; the host side is marked DISABLED whatever happens."""
        answer_only = confirm and not self.confirms_disable and self._last_heartbeat is not None
        if answer_only:
            self._drain_before_stop()
        results = [self._send_safely("zero torque", partial(self._torque_frame, 0.0))]
        try:
            names = tuple(self._disable_frame_names())
        except Exception:  # safety path: a broken hook still gets its frame attempted
            names = (self.disabled_state_text,)
        for i, name in enumerate(names):
            results.append(self._send_safely(name, partial(self._disable_frame, i)))
        failed = [r for r in results if not r.sent]
        if failed:
            detail = "; ".join(f"{r.what} frame not sent ({r.error})" for r in failed)
            report = SafeStopReport(self.node_id, tuple(results), Confirmation.NOT_SENT, detail)
        elif not confirm:
            report = SafeStopReport(self.node_id, tuple(results), Confirmation.NOT_ASKED)
        elif self._last_heartbeat is None and self._enable_sent:
            report = self._await_first_answer(tuple(results), timeout, cancel)
        elif self._last_heartbeat is None:
            report = SafeStopReport(self.node_id, tuple(results), Confirmation.NEVER_SEEN)
        elif answer_only:
            report = self._await_answer(tuple(results), timeout, cancel)
        else:
            report = self._confirm_disabled(tuple(results), timeout, cancel)
        if planned:
            report = replace(report, planned=True)
        verdict = "cannot be confirmed" if report.confirmation is Confirmation.UNCONFIRMABLE else "failed"
        failure = "" if report.safe else f"disable of node {self.node_id} {verdict}: {report.detail}"
        self._set_state(DriveState.DISABLED, failure)
        return report

    def send_torque(self, tau_nm: float) -> None:
        """Send one torque command [Nm]; non-blocking. Clamping is the controller's job.
        Raises BusError when the bus refuses the frame (ENOBUFS, interface gone)."""
        if not math.isfinite(tau_nm):
            raise DriveError(f"torque: expected a finite value in Nm, got {tau_nm!r}")
        if self._state is not DriveState.ENABLED:
            self._raise_not_enabled()
        frame = self._torque_frame(tau_nm)
        try:
            self._bus.send(frame, 0.0)
        except Exception as exc:  # whatever the interface raises: python-can-remote, say,
            # raises its own transport errors when the hub is gone
            raise BusError(f"torque frame to node {self.node_id} not sent: {_bus_failure(exc)}") from exc

    def poll(self, timeout: float) -> Feedback | None:
        """Read frames for up to ``timeout`` s; return the newest fresh feedback or None.

        Everything already queued is read first; the call returns as soon as a
        motion frame has been read, with whatever came queued behind it (a burst of late
        frames gives its newest), and a wait that ends late (the process was stopped)
        reads all that came meanwhile. Raises DriveFaultError while the drive is faulted.
        """
        fresh = self._drain()
        if not fresh and timeout > 0:
            fresh = self._wait_for_motion(self._clock() + timeout)
            if fresh:
                self._drain()
        now = self._clock()
        self._unread, self._read_at = now - self._read_at, now
        gaps = self._gaps
        if fresh:
            gaps.clear()
        else:   # (a later gap as long hides an earlier one: the later return is what counts)
            while gaps and gaps[-1][0] <= self._unread:
                gaps.pop()
            gaps.append((self._unread, now))
        if self._state is DriveState.ENABLED:
            self._check_heartbeat(now)
        if self._state is DriveState.FAULT:
            raise DriveFaultError(self._detail)
        return self._feedback if fresh else None

    def since_back(self, gap: float) -> float:
        """[s] How long ago the host came back from going ``gap`` s or longer without
        reading the bus, since the last :meth:`poll` that read fresh motion feedback; inf
        if it did not. A gap between reads runs from the end of one poll to the end of
        the next, that poll's own wait included: about the loop's period while the host
        keeps up, longer when its process was stopped or not run. A silence of the drive
        over a span the host did not read is not yet the drive's -- what was sent meanwhile
        may still be on its way (a python-can-remote hub forwards it late) -- so a caller
        timing the feedback counts its timeout from this return."""
        for length, end in reversed(self._gaps):
            if length >= gap:
                return self._clock() - end
        return math.inf

    def _check_heartbeat(self, now: float) -> None:
        """A drive whose status frames stop is a fault, even if motion frames still come.

        The watch is HEARTBEAT_MISSES periods of silence. When the host itself read
        nothing for that long (its process was stopped or not run), the
        frames the drive sent meanwhile may still be on their way -- a python-can-remote
        hub or a busy kernel forwards them late -- so the silence is the drive's only once
        it has lasted the watch again from the host's first read back (the drive's status
        then, its watchdog's expiry say, is what the host reports). Nothing here waits."""
        rate = self._profile.heartbeat_period
        last = self._last_heartbeat
        if last is None or rate is None or rate <= 0:
            return  # no heartbeat watched
        watch = HEARTBEAT_MISSES * rate
        silent = now - last
        if silent <= watch:
            self._back_at = None
            return
        if self._back_at is None and self._unread > watch:
            self._back_at = now
        if self._back_at is not None and now - self._back_at <= watch:
            return
        self._set_state(DriveState.FAULT,
                        f"no heartbeat from node {self.node_id} for {silent:.3f} s "
                        f"(expected every {rate:g} s)")

    @property
    def confirms_disable(self) -> bool:
        """True when this drive's frames can confirm that it left torque control (ODrive's
        heartbeat, CiA 402's statusword). False (a CubeMars AK in MIT mode: its replies carry
        no mode): a safe stop that asks for a confirmation reports
        :attr:`Confirmation.UNCONFIRMABLE`, not safe, with :meth:`_unconfirmable_detail`."""
        return True

    def __enter__(self) -> Drive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.disable()

    # -- protocol hooks -------------------------------------------------------

    def _prepare(self, deadline: float, cancel: Cancel | None) -> None:
        """Start-up before any torque (CiA 402: NMT, SDO reads, PDO mapping, SYNC start),
        done by ``deadline`` (drive clock) and cancellable between slices of WAIT_SLICE s.
        Raises DriveError (one line: node, object, state reached), BusError or
        WaitCancelled. Default: nothing to prepare."""
        return None  # (a hook, not abstract: ODrive has nothing to prepare)

    def _read_queued(self, deadline: float) -> None:
        """Read what is queued, decoded as usual, and forget the state it reported: for a
        drive that only answers commands, a reply sent before the enable must not be taken
        for the enable's answer (nor quoted by its timeout's line). Bounded by ``deadline``:
        a bus that never runs dry (another host's traffic) is read until then."""
        recv = self._bus.recv
        while self._clock() < deadline:
            try:
                msg = recv(0.0)
            except Exception as exc:  # any interface's failure is the bus's
                raise self._read_error(exc) from exc
            if msg is None:
                break
            self._handle(msg)
        self._last_state = None

    @abstractmethod
    def _enable_start(self) -> Sequence[can.Message]:
        """Frames that start the enable handshake, in order."""

    def _enable_step(self, event: StateEvent) -> Sequence[can.Message]:
        """Frames to send next, given a state the drive reported while enable() waits
        (a CiA 402 controlword for its power state). May raise DriveFaultError or
        DriveError to end the enable at once (a fault it must not clear). Default: none."""
        return ()

    @abstractmethod
    def _disable_frames(self) -> Sequence[can.Message]:
        """Frames that take the drive out of torque control (after a zero torque)."""

    @abstractmethod
    def _torque_frame(self, tau_nm: float) -> can.Message:
        """The torque command frame (may be a preallocated message, refilled)."""

    @abstractmethod
    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        """Events in one received frame; () for frames not from this drive."""

    def _status_request_frames(self) -> Sequence[can.Message]:
        """Frames that ask the drive for a status frame now, sent every
        STATUS_REQUEST_INTERVAL s while the safe stop waits for its confirmation (an ODrive
        0.6 answers a heartbeat RTR): without them the wait lasts until the drive's next
        cyclic status frame, up to a whole ``heartbeat_period``. Default: none."""
        return ()

    def _keepalive_frames(self) -> Sequence[can.Message]:
        """Frames repeated while enable() waits: keep the drive's watchdog fed and ask
        for status. Default: a zero torque command."""
        return (self._torque_frame(0.0),)

    def _is_enabled_confirmation(self, event: StateEvent) -> bool:
        """True if ``event`` confirms the enable handshake."""
        return event.active and event.error_code == 0

    @classmethod
    def preflight_probe(cls, profile: DriveProfile) -> PreflightProbe | None:
        """The protocol's preflight hooks (:mod:`dobhil.drives.preflight`): how to read
        its frames and name its settings. None: no preflight for this protocol yet."""
        return None

    def _is_disabled_confirmation(self, event: StateEvent) -> bool:
        """True if ``event`` (received after the disable frames) confirms the disable."""
        return not event.active

    def _host_watch_of(self, event: StateEvent | None) -> HostTimeout | None:
        """The drive's watch on the host's frames (:class:`HostTimeout`): with ``event``
        None, the one configured; with a fault ``event``, the watch only if that fault is
        it expiring (an ODrive's WATCHDOG_TIMER_EXPIRED, a CiA 402 heartbeat-consumer
        EMCY), else None. Default: the drive watches nothing of the host's."""
        return None

    def _unconfirmable_detail(self) -> str:
        """Why the disable cannot be confirmed, one line (only asked when
        :attr:`confirms_disable` is False); it follows what the answer showed in the note
        or the loud line (``"<shown>, but <this>"``)."""
        return f"protocol {self.protocol!r} cannot confirm it: its frames carry no drive state"

    def _disable_answer(self, received: Sequence[can.Message], sent: int) -> tuple[bool, str]:
        """What the drive's frames received since the ``sent`` safe-stop frames went out
        (only frames that decoded to events of this drive, oldest first) confirm, for a
        drive that cannot confirm its disable (:attr:`confirms_disable` False): ``(done,
        one line)``, done when the answer is all the protocol can give; the line says what
        was seen either way ("" for nothing). Default: any frame of the drive answers."""
        if not received:
            return False, ""
        return True, f"{self.disabled_state_text} sent and node {self.node_id} answered"

    def _disable_frame(self, index: int) -> can.Message:
        return self._disable_frames()[index]

    def _disable_frame_names(self) -> Sequence[str]:
        """A name per disable frame, for the safe-stop report."""
        count = len(self._disable_frames())
        if count == 1:
            return (self.disabled_state_text,)
        return tuple(f"{self.disabled_state_text} {i + 1}/{count}" for i in range(count))

    # -- internals ------------------------------------------------------------

    def _send_all(self, frames: Sequence[can.Message], what: str) -> None:
        for frame in frames:
            try:
                self._bus.send(frame)
            except Exception as exc:  # any interface's failure (see send_torque)
                raise BusError(f"{what} frames to node {self.node_id} not sent: {_bus_failure(exc)}") from exc

    def _recv(self, timeout: float) -> can.Message | None:
        """``bus.recv`` outside the cycle; any failure of the bus is a BusError."""
        try:
            return self._bus.recv(timeout)
        except Exception as exc:  # python-can's, the OS's or a transport's own error
            raise self._read_error(exc) from exc

    def _send_safely(self, what: str, make: Callable[[], can.Message]) -> FrameResult:
        """One safe-stop frame, retried while the bus refuses it, for up to SAFE_STOP_RETRY s
        of wall time and at least SAFE_STOP_ATTEMPTS attempts. Never raises."""
        give_up = time.monotonic() + SAFE_STOP_RETRY
        refused = 0
        while True:
            try:
                self._bus.send(make())
                return FrameResult(what, True, refused=refused)
            except Exception as exc:  # safety path: every frame gets its own attempt
                refused += 1
                error = exception_line(exc, named=False)
                if refused >= SAFE_STOP_ATTEMPTS and time.monotonic() >= give_up:
                    return FrameResult(what, False, error, refused)
                time.sleep(0.001)

    def _drain_before_stop(self) -> None:
        """Read what is queued before the safe-stop frames (at most a bounded number of
        frames: a bus that never runs dry cannot hold the stop): an answer that was on its
        way before them answers none of them. Never raises."""
        try:
            for _ in range(DRAIN_LIMIT):
                msg = self._bus.recv(0.0)
                if msg is None:
                    return
                self._handle(msg)
        except Exception:  # safety path: an unreadable bus still gets its safe-stop frames
            return

    def _await_answer(self, frames: tuple[FrameResult, ...], timeout: float | None,
                      cancel: Cancel | None) -> SafeStopReport:
        """Read the drive's frames until :meth:`_disable_answer` is done with them
        (UNCONFIRMABLE: what they showed, and why that is not a confirmation) or the wait
        ends (NOT_ACKNOWLEDGED)."""
        wait = self._confirm_timeout() if timeout is None else timeout
        received: list[can.Message] = []
        shown = ""

        def answered(msg: can.Message) -> bool:
            nonlocal shown
            events = self._decode(msg)
            for event in events:
                if isinstance(event, MotionEvent):
                    self._on_motion(event)
                else:
                    self._record_state(event)
            if not events:
                return False
            received.append(msg)
            done, shown = self._disable_answer(received, len(frames))
            return done

        why = self._read_until(wait, cancel, answered, silence=f"no answer within {wait:g} s")
        if not why:
            return SafeStopReport(self.node_id, frames, Confirmation.UNCONFIRMABLE,
                                  f"{shown}, but {self._unconfirmable_detail()}")
        seen = f"{shown}; " if shown else ""
        return SafeStopReport(self.node_id, frames, Confirmation.NOT_ACKNOWLEDGED,
                              f"did not answer {self.disabled_state_text} ({seen}{why})")

    def _read_until(self, wait: float, cancel: Cancel | None, done: Callable[[can.Message], bool], *,
                    silence: str, requests: Sequence[can.Message] = ()) -> str:
        """Read frames for up to ``wait`` s until ``done(frame)``: "" then, else why not
        (``silence`` when the wait ended, the wait cancelled, the bus unreadable).
        ``requests``: frames sent before the first read and every STATUS_REQUEST_INTERVAL s.
        Past the deadline only what is already queued is read. Never raises."""
        between = partial(self._send_requests, requests) if requests else None
        frames = sliced_frames(self._bus.recv, self._clock, self._clock() + wait, cancel=cancel, drain=True,
                               between=between, every=STATUS_REQUEST_INTERVAL)
        try:
            return "" if any(done(msg) for msg in frames) else silence
        except WaitCancelled as exc:
            return f"confirmation wait cut short: {exc}"
        except Exception as exc:  # safety path: a bus that cannot be read confirms nothing
            return f"status not readable: {exc}"

    def _send_requests(self, frames: Sequence[can.Message]) -> None:
        """Status requests of a confirmation wait. Never raises: a request the bus refuses
        leaves the wait to the drive's cyclic status frames."""
        for frame in frames:
            try:
                self._bus.send(frame)
            except Exception:  # safety path: the wait goes on without it
                return

    def _await_first_answer(self, frames: tuple[FrameResult, ...], timeout: float | None,
                            cancel: Cancel | None) -> SafeStopReport:
        """The safe stop of a drive sent its enable frames but never heard from: waited for
        as any drive's (one slow to speak -- just powered, its emulator still starting --
        may answer now and confirm its disable, or show what its protocol can show); heard
        from nothing to the end: NEVER_ANSWERED, never safe."""
        if self.confirms_disable:
            report = self._confirm_disabled(frames, timeout, cancel)
        else:
            report = self._await_answer(frames, timeout, cancel)
        if self._last_heartbeat is not None:
            return report
        return SafeStopReport(self.node_id, frames, Confirmation.NEVER_ANSWERED, self._never_answered_detail())

    def _never_answered_detail(self) -> str:
        """Why a drive sent its enable frames but never heard from is not safe, one line."""
        return (f"never answered: its enable frames (for {self.active_state_text}) went out and nothing was "
                f"heard from it since, so {self.disabled_state_text} cannot be confirmed")

    def _confirm_timeout(self) -> float:
        rate = self._profile.heartbeat_period
        return HEARTBEAT_MISSES * rate if rate else self._profile.enable_timeout

    def _confirm_disabled(self, frames: tuple[FrameResult, ...], timeout: float | None,
                          cancel: Cancel | None) -> SafeStopReport:
        """Read status frames until one says the drive left torque control (or the
        wait is cancelled)."""
        wait = self._confirm_timeout() if timeout is None else timeout
        seen: StateEvent | None = None

        def confirmed(msg: can.Message) -> bool:
            nonlocal seen
            for event in self._decode(msg):
                if isinstance(event, MotionEvent):
                    self._on_motion(event)
                    continue
                self._record_state(event)
                seen = event
                if self._is_disabled_confirmation(event):
                    return True
            return False

        silence = f"no status frame within {wait:g} s"
        try:
            requests = tuple(self._status_request_frames())
        except Exception:  # safety path: a broken hook leaves the wait to the cyclic frames
            requests = ()
        why = self._read_until(wait, cancel, confirmed, silence=silence, requests=requests)
        if not why:
            return SafeStopReport(self.node_id, frames, Confirmation.CONFIRMED)
        if seen is not None and why == silence:
            why = f"still {seen.state_text} after {wait:g} s"
        return SafeStopReport(self.node_id, frames, Confirmation.NOT_ACKNOWLEDGED,
                              f"did not acknowledge {self.disabled_state_text} ({why})")

    def _keepalive_interval(self) -> float:
        watchdog = self._profile.watchdog_timeout
        if watchdog > 0:
            return watchdog / 4
        return self._profile.heartbeat_period or DEFAULT_KEEPALIVE

    def _await_enabled(self, deadline: float, cancel: Cancel | None) -> bool:
        frames = sliced_frames(self._recv, self._clock, deadline, cancel=cancel,
                               what=f"waiting for node {self.node_id} to enable",
                               between=lambda: self._send_all(self._keepalive_frames(), "keepalive"),
                               every=self._keepalive_interval())
        return any(self._handle_for_enable(msg) for msg in frames)

    def _drain(self) -> bool:
        fresh = False
        recv = self._bus.recv
        while True:
            try:
                msg = recv(0.0)
            except Exception as exc:  # any interface's read failure is the bus's
                raise self._read_error(exc) from exc
            if msg is None:
                return fresh
            fresh = self._handle(msg) or fresh

    def _wait_for_motion(self, deadline: float) -> bool:
        while True:
            remaining = deadline - self._clock()
            if remaining <= 0:
                # the deadline passed while a read blocked (this process stopped or not
                # scheduled): what the bus queued meanwhile -- sent on time by a kernel
                # periodic task and the drive -- is read before the caller takes the
                # silence for a drive gone quiet (the heartbeat watch, a feedback timeout)
                return self._drain()
            try:  # inline, not _recv: one call less per cycle
                msg = self._bus.recv(remaining)
            except Exception as exc:
                raise self._read_error(exc) from exc
            if msg is None:
                return False
            if self._handle(msg):
                return True

    def _read_error(self, exc: BaseException) -> BusError:
        return BusError(f"bus read for node {self.node_id} failed: {_bus_failure(exc)}")

    def apply(self, msg: can.Message) -> bool:
        """Apply one frame received elsewhere (a recorded one: replay); True if it carried
        motion feedback."""
        return self._handle(msg)

    def _handle(self, msg: can.Message) -> bool:
        """Apply one frame; True if it carried motion feedback."""
        fresh = False
        for event in self._decode(msg):
            if isinstance(event, MotionEvent):
                self._on_motion(event, msg.timestamp)
                fresh = True
            else:
                self._on_state(event)
        return fresh

    def _handle_for_enable(self, msg: can.Message) -> bool:
        confirmed = False
        for event in self._decode(msg):
            if isinstance(event, MotionEvent):
                self._on_motion(event)
                continue
            self._record_state(event)
            try:
                frames = self._enable_step(event)
            except DriveFaultError as exc:
                self._set_state(DriveState.FAULT, str(exc))
                raise
            if frames:
                self._send_all(frames, "enable step")
            confirmed = confirmed or self._is_enabled_confirmation(event)
        return confirmed

    def _on_motion(self, event: MotionEvent, rx_time: float = math.nan) -> None:
        self._seq += 1
        self._feedback = Feedback(self._clock(), event.position, event.velocity, self._seq,
                                  rx_time or math.nan, event.sampled_at)

    def _record_state(self, event: StateEvent) -> None:
        self._last_state = event
        self._last_heartbeat = self._clock()
        self._status_cache = None

    def _on_state(self, event: StateEvent) -> None:
        self._record_state(event)
        if self._state is not DriveState.ENABLED:
            return
        if event.watchdog_tripped:
            self._watchdog_expired = True
            self._status_cache = None
        if event.error_code != 0 or not event.active:
            self._set_state(DriveState.FAULT, self._fault_text(event))
            self._fault_event = event

    def _fault_text(self, event: StateEvent) -> str:
        what = "watchdog expired" if event.watchdog_tripped else "fault"
        return (
            f"node {self.node_id} {what}: expected {self.active_state_text} with no error, "
            f"got {event.state_text} with error {event.error_text}"
        )

    def _set_state(self, state: DriveState, detail: str) -> None:
        self._state = state
        self._detail = detail
        self._fault_event = None
        self._status_cache = None

    def _raise_not_enabled(self) -> None:
        if self._state is DriveState.FAULT:
            raise DriveFaultError(self._detail)
        raise DriveError(f"send_torque needs an enabled drive, node {self.node_id} is DISABLED")

    def _enable_timeout_text(self, wait: float) -> str:
        last = self._last_state
        if last is None:
            return (
                f"no heartbeat from node {self.node_id} within {wait:g} s "
                f"(waiting for {self.active_state_text})"
            )
        return (
            f"node {self.node_id} not enabled within {wait:g} s: expected "
            f"{self.active_state_text} with no error, last seen {last.state_text} "
            f"with error {last.error_text}"
        )


def _bus_failure(exc: BaseException) -> str:
    """A bus failure as one line: python-can's and the OS's errors say enough alone, a
    transport's own needs its type named (``Status: 1006, reason: Socket closed
    unexpectedly`` says little)."""
    return exception_line(exc, named=not isinstance(exc, (can.CanError, OSError)))
