"""Recording under stress: a flood of foreign frames on the run's own bus, in real time."""

from __future__ import annotations

import random
import threading
import time
from pathlib import Path

import can

from dobhil.cli.recording import open_run_log, record_run
from dobhil.config import load_config
from dobhil.recording.reader import open_log
from dobhil.runtime.session import RunSession
from tests.runtime.helpers import write_profile

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "configs" / "demo.yaml"
NODE_IDS = range(3 << 5, 4 << 5)  # node 3's ODrive ids
ENCODER, TORQUE = (3 << 5) | 0x09, (3 << 5) | 0x0E
#: The drive's frames per second (encoder every 5 ms, heartbeat every 50 ms) and the flood's.
DRIVE_RATE = 1 / 5e-3 + 1 / 0.05
FLOOD_PER_DRIVE_FRAME = 100


def foreign_frames(n: int) -> list[can.Message]:
    """Other participants' frames: standard ids outside node 3's, extended ids, remote frames."""
    rng, out = random.Random(7), []
    while len(out) < n:
        extended = rng.random() < 0.25
        arb = rng.randrange(1 << 29) if extended else rng.randrange(0x800)
        if extended or arb not in NODE_IDS:
            size = rng.randrange(9)
            out.append(can.Message(arbitration_id=arb, is_extended_id=extended, is_remote_frame=rng.random() < 0.1,
                                   dlc=size, data=bytes(rng.randrange(256) for _ in range(size))))
    return out


class WithForeign(can.BusABC):
    """The run's bus with other participants on it: what they send on ``channel`` (a
    ``virtual`` channel) is received here among the drive's frames. A real-time emulated
    drive is a process of its own joined to the loop by a socket pair, so a flood cannot
    share that pair; this puts it on the loop's side of the bus, where a real bus has it."""

    def __init__(self, host: can.BusABC, channel: str) -> None:
        self.host = host
        self.others = can.Bus(interface="virtual", channel=channel)
        super().__init__(channel=host.channel_info)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.host.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.perf_counter() + timeout
        while True:
            msg = self.others.recv(0)
            if msg is not None:
                return msg, False
            left = None if deadline is None else deadline - time.perf_counter()
            if left is not None and left <= 0:
                return None, False
            msg = self.host.recv(1e-3 if left is None else min(left, 1e-3))
            if msg is not None:
                return msg, False

    def shutdown(self) -> None:
        self.others.shutdown()   # the host bus is the session's: it shuts that down
        super().shutdown()


class Flood:
    """A participant of the bus sending ``rate`` foreign frames per second, in bursts every 5 ms."""

    def __init__(self, channel: str, rate: float) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames, self.per_burst = foreign_frames(512), round(rate * 5e-3)
        self.sent, self.seconds = 0, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self, _log: object = None) -> None:
        self._thread.start()

    def _run(self) -> None:
        start = next_burst = time.perf_counter()
        frames, n = self.frames, len(self.frames)
        while not self._stop.is_set():
            for _ in range(self.per_burst):
                self.bus.send(frames[self.sent % n])
                self.sent += 1
            next_burst += 5e-3
            time.sleep(max(0.0, next_burst - time.perf_counter()))
            self.seconds = time.perf_counter() - start

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self.bus.shutdown()


def test_a_bus_flood_sheds_foreign_frames_and_keeps_every_record_of_the_loop(tmp_path: Path) -> None:
    """A real-time emulated run recorded while another participant floods its bus with 100x
    the drive's frame rate: every cycle (its /loop, /controller, /drive/command and
    /drive/feedback), every torque command sent and every drive frame the loop read is in
    the log; foreign frames are shed and counted (loss events = metadata), never a record
    of the loop. (The drive runs at 200 Hz: the flood is 22,000 frames/s, what one Python
    thread sends here; the loop overruns and skips cycles under it, and records each it runs.)"""
    profile = write_profile(tmp_path, "odrive-0.6", feedback_period=5e-3, heartbeat_period=0.05,
                            watchdog_timeout=0.5, enable_timeout=5.0)
    config = load_config(DEMO, [f"drive.profile={profile}", "loop.period=5e-3", "loop.feedback_timeout=0.2",
                                "design.dob_bandwidth=100", "design.rtob_bandwidth=100", "loop.duration=3"])
    path = tmp_path / "flood.mcap"
    log = open_run_log(path, fsync=False)
    assert log is not None
    channel, joined = f"flood-{time.monotonic_ns()}-x", []

    def join(bus: can.BusABC) -> can.BusABC:
        joined.append(WithForeign(bus, channel))
        return log.wrap_bus(joined[-1])

    with RunSession(config, emulate=True, lockstep=False, sink=log, bus_wrapper=join) as session:
        flood = Flood(channel, FLOOD_PER_DRIVE_FRAME * DRIVE_RATE)
        try:
            result = record_run(session, log, DEMO, on_begin=flood.start)
        finally:
            flood.stop()
            for bus in joined:
                bus.shutdown()
    with open_log(path) as recorded:
        counts = recorded.message_counts()
        rx = [p["arbitration_id"] for _, _, p in recorded.iter_messages(["/can/rx"])]
        tx = [p["arbitration_id"] for _, _, p in recorded.iter_messages(["/can/tx"])]
        seq = max(p["seq"] for _, _, p in recorded.iter_messages(["/drive/feedback"]))
        events = [p for _, _, p in recorded.iter_messages(["/events"])]
        dropped = int(recorded.metadata["recording"]["dropped"])
    cycles, losses = result.cycles, [e for e in events if e["kind"] == "loss"]
    foreign = sum(1 for arb in rx if arb not in NODE_IDS)
    print(f"flood {flood.sent / flood.seconds:.0f} frames/s for {flood.seconds:.1f} s; {cycles} cycles; "
          f"{foreign} foreign frames recorded, {dropped} shed")
    assert cycles > 0 and dropped > 0  # the flood was more than the recorder takes
    for topic in ("/loop", "/controller", "/drive/command"):
        assert counts[topic] == cycles, (topic, counts, result.stop.line())
    assert counts["/drive/feedback"] == cycles + 1
    assert tx.count(TORQUE) >= cycles  # one torque command per cycle, and the safe stop's
    assert rx.count(ENCODER) >= seq  # every motion frame the drive object counted
    assert all("foreign" in e["reason"] for e in losses) and sum(e["count"] for e in losses) == dropped
    assert foreign + dropped <= flood.sent
