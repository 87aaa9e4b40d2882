"""Shared by the runtime tests: configs, relaxed real-time profiles, a bus sniffer,
the safe-stop checks and a condition wait (never a wall-clock assertion)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import can
import numpy as np
import yaml

from dobhil.config import Config, load_config
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, Firmware
from dobhil.runtime.loop import Timing
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import Stop, StopReason

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "configs" / "demo.yaml"
DRIVERS = REPO / "drivers"
FIRMWARES = ("odrive-0.6", "odrive-0.5")
NODE = 3

#: contact from the start (q0 = q_c = 0) and a 1 N m step from t = 0: the analysed loop
STEP_FROM_ZERO = ("plant.initial_position=0", "reference.offset=0", "reference.amplitude=1",
                  "reference.start=0")
#: real time on a loaded 2-core CI machine: a generous feedback timeout
REALTIME_SLACK = ("loop.feedback_timeout=0.05",)


def demo_config(*overrides: str) -> Config:
    return load_config(DEMO, list(overrides))


def write_profile(tmp_path: Path, name: str, **changes: object) -> Path:
    """A copy of ``drivers/<name>.yaml`` with ``changes`` (firmware, node id ... kept)."""
    data = yaml.safe_load((DRIVERS / f"{name}.yaml").read_text(encoding="utf-8"))
    data.update(changes)
    data["bus"] = {}
    path = tmp_path / f"{name}-{'-'.join(sorted(changes)) or 'copy'}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def realtime_profile(tmp_path: Path, name: str, **changes: object) -> Path:
    """The shipped profile with only the drive watchdog and enable wait relaxed, so a
    scheduling hiccup of a loaded CI machine is not a drive fault (rates unchanged)."""
    return write_profile(tmp_path, name, **{"watchdog_timeout": 0.25, "enable_timeout": 2.0,
                                            **changes})


def wait_until(condition: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` s pass (a bound, not a measurement)."""
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            return condition()
        time.sleep(0.005)
    return True


@dataclass(frozen=True)
class HostCommands:
    """What the host sent to the node, decoded."""

    torques: list[float]
    axis_states: list[int]
    estops: int


class Sniffer:
    """An extra ``virtual`` bus on a channel: sees every frame the others send."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[can.Message] = []

    def drain(self) -> list[can.Message]:
        msg = self.bus.recv(0.0)
        while msg is not None:
            self.frames.append(msg)
            msg = self.bus.recv(0.0)
        return self.frames

    def host_commands(self, firmware: Firmware, node: int = NODE) -> HostCommands:
        torques: list[float] = []
        states: list[int] = []
        estops = 0
        for msg in self.drain():
            got_node, cmd = codec.split_id(msg.arbitration_id)
            if got_node != node or msg.is_remote_frame:
                continue
            if cmd == CmdId.SET_INPUT_TORQUE:
                torques.append(codec.decode_message(msg, firmware).torque_nm)
            elif cmd == CmdId.SET_AXIS_STATE:
                states.append(int(codec.decode_message(msg, firmware).requested_state))
            elif cmd == CmdId.ESTOP:
                estops += 1
        return HostCommands(torques, states, estops)

    def close(self) -> None:
        self.bus.shutdown()

    def __enter__(self) -> Sniffer:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def firmware_of(session: RunSession) -> Firmware:
    return Firmware.parse(session.profile.firmware)


def settle_emulator(session: RunSession) -> bool:
    """Let the emulator take the frames in flight (the disable); True once it is IDLE
    with zero torque. Lockstep: it reads what is pending; real time: wait for its thread."""
    emu = session.emulator
    assert emu is not None

    def idle() -> bool:
        return emu.protocol_state == AxisState.IDLE and emu.applied_torque == 0.0  # type: ignore[attr-defined]

    if session.timing is Timing.LOCKSTEP:
        emu.handle_pending()
        return idle()
    return wait_until(idle)


def assert_stopped_safely(session: RunSession, sniffer: Sniffer, stop: Stop,
                          reason: StopReason, *, words: Iterable[str] = (),
                          emulated: bool = True) -> HostCommands:
    """The checks every stop must pass: why, in one line; zero torque was the last torque
    command; IDLE was requested last; the emulated drive ends IDLE with zero torque."""
    line = stop.line()
    assert stop.reason is reason, line
    assert "\n" not in line and reason.name.lower() in line
    for word in words:
        assert word.lower() in line.lower(), (word, line)
    sent = sniffer.host_commands(firmware_of(session))
    assert sent.torques and sent.torques[-1] == 0.0, sent.torques[-3:]
    assert sent.axis_states and sent.axis_states[-1] == AxisState.IDLE, sent.axis_states
    if emulated:
        assert settle_emulator(session), "emulator not IDLE with zero torque after the stop"
    return sent


def finite_tail(values: np.ndarray, t: np.ndarray, seconds: float, *,
                at_least: int = 10) -> np.ndarray:
    """The finite samples of the last ``seconds`` (skipped deadlines are NaN rows), or
    the last ``at_least`` finite samples when fewer cycles ran in that time: a host the
    machine did not schedule for ``seconds`` skips every cycle due meanwhile and runs one
    at the end, and the tail is then made of the cycles the run did measure, not of a
    count the test assumed."""
    finite = np.flatnonzero(np.isfinite(values))
    recent = np.flatnonzero(np.isfinite(values) & (t >= t[np.isfinite(t)][-1] - seconds))
    keep = recent if recent.size >= at_least else finite[-at_least:]
    return values[keep]


def summary_shape(value: Any) -> Any:
    """A run summary's keys and value types, recursively (lists: their first item's): what
    must be the same for every protocol, whatever the values."""
    if isinstance(value, dict):
        return {k: summary_shape(v) for k, v in value.items()}
    if isinstance(value, list):
        return [summary_shape(v) for v in value[:1]]
    return type(value).__name__ if value is not None else None


@dataclass(frozen=True)
class HostWatchCase:
    """A profile whose drive times the host's frames out (``DriveProtocol.host_watch``), a
    ``loop.period`` of half that timeout (the shortest one refused) and the refusal's words."""

    profile: str        # a shipped profile's name or a written profile's path
    name: str           # the profile's name in the refusal
    period: float       # [s] timeout / 2
    what: str
    key: str
    timeout: float

    def refusal(self, prefix: str = "") -> str:
        """The refusal's line up to its remedy (which the protocol words)."""
        return (f"{prefix}loop.period = {self.period:g} s is too long for the {self.what} of drive profile "
                f"{self.name!r} ({self.key} = {self.timeout:g} s")

    def allowed(self) -> str:
        return f"allowed: loop.period < {self.timeout / 2:g} s (half of {self.key}), or "


def damiao_with_timeout(tmp_path: Path, timeout: float) -> Path:
    """A DM4310 profile whose model row has a command timeout of ``timeout`` s (the TIMEOUT
    register set; the shipped rows say null, the factory's 0), on the config's own bus."""
    table = yaml.safe_load((DRIVERS / "mit-models.yaml").read_text(encoding="utf-8"))
    (row,) = [r for r in table["models"] if (r["vendor"], r["model"]) == ("damiao", "DM4310")]
    row["command_timeout"] = timeout
    models = tmp_path / "mit-models.yaml"
    models.write_text(yaml.safe_dump(table), encoding="utf-8")
    damiao = yaml.safe_load((DRIVERS / "dm4310.yaml").read_text(encoding="utf-8"))
    damiao["mit"]["models"] = str(models)
    damiao["bus"] = {}
    profile = tmp_path / "dm4310-timeout.yaml"
    profile.write_text(yaml.safe_dump(damiao), encoding="utf-8")
    return profile


def host_watch_cases(tmp_path: Path) -> dict[str, HostWatchCase]:
    """One case per protocol that has such a timeout: an ODrive's and a moteus' command
    watchdog (``watchdog_timeout``), a CiA 402 node's heartbeat consumer
    (``cia402.consumer_heartbeat``), an MIT motor's command timeout (its model row's
    ``command_timeout``: the shipped Mini-Cheetah row's, and a Damiao row of the user's own
    with its TIMEOUT register set)."""
    consumer = yaml.safe_load((DRIVERS / "cia402-emulated.yaml").read_text(encoding="utf-8"))
    consumer["cia402"].update(consumer_heartbeat=0.05, eds=str(DRIVERS / "cia402-emulated.eds"))
    consumer["bus"] = {}
    cia402 = tmp_path / "cia402-consumer.yaml"
    cia402.write_text(yaml.safe_dump(consumer), encoding="utf-8")
    dm = damiao_with_timeout(tmp_path, 0.02)
    return {
        "odrive": HostWatchCase("odrive-0.6", "odrive-0.6", 0.025, "command watchdog", "watchdog_timeout", 0.05),
        "moteus": HostWatchCase("moteus-r4.11", "moteus-r4.11", 0.05, "command watchdog", "watchdog_timeout", 0.1),
        "cia402": HostWatchCase(str(cia402), "cia402-consumer", 0.025, "heartbeat consumer (0x1016)",
                                "cia402.consumer_heartbeat", 0.05),
        "mit-mini-cheetah": HostWatchCase("mini-cheetah", "mini-cheetah", 0.0125, "command timeout",
                                          "command_timeout", 0.025),
        "mit-damiao": HostWatchCase(str(dm), "dm4310-timeout", 0.01, "command timeout", "command_timeout", 0.02),
    }


#: the protocols of :func:`host_watch_cases`
HOST_WATCHES = ("odrive", "moteus", "cia402", "mit-mini-cheetah", "mit-damiao")
