"""``can.Bus(interface="dobhil", channel=...)``: the emulated drive behind a python-can bus,
driven by plain python-can and by odrive-can's own ``ODriveCAN`` client."""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from dobhil.canio.bus import DobhilBus, EmulatedBusError, override_items
from dobhil.config import resolve_config
from dobhil.data import shipped_configs

REPO = Path(__file__).resolve().parents[2]
NODE = 3  # drivers/odrive-0.6.yaml
TURN = 2.0 * math.pi
BOUND = 5.0  # s: how long a loaded CI machine may take, not a measurement


def wait_until(condition: Callable[[], bool], timeout: float = BOUND) -> bool:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def relaxed_profile(tmp_path: Path) -> Path:
    """drivers/odrive-0.6.yaml with a 0.5 s watchdog and encoder estimates every 10 ms:
    a scheduling hiccup of a loaded machine must not trip the watchdog, and odrive-can
    hands every frame to its asyncio loop one by one (node, firmware, heartbeat unchanged)."""
    data = yaml.safe_load((REPO / "drivers" / "odrive-0.6.yaml").read_text(encoding="utf-8"))
    data.update(watchdog_timeout=0.5, feedback_period=0.01, bus={})
    path = tmp_path / "odrive-0.6-relaxed.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_registered_as_a_python_can_interface() -> None:
    assert "dobhil" in can.VALID_INTERFACES
    before = set(threading.enumerate())
    found = can.detect_available_configs("dobhil")
    # python-can's detection leaves its thread pool to finish by itself
    assert wait_until(lambda: not [t for t in threading.enumerate() if t not in before])
    assert {c["channel"] for c in found} == set(shipped_configs())
    assert {"demo", "paper/fig2c"} <= set(shipped_configs())
    assert all(c["interface"] == "dobhil" for c in found)


def official_dbc() -> object:
    """The official ODrive 0.6.10 DBC shipped with odrive-can, read by cantools: frames
    are checked against it, not against dobhil's own codec."""
    cantools = pytest.importorskip("cantools")
    odrive_can = pytest.importorskip("odrive_can")
    dbc = Path(odrive_can.__file__).resolve().parent / "dbc" / "odrive-cansimple-0.6.10.dbc"
    return cantools.database.load_file(str(dbc))


def test_heartbeat_rtr_and_shutdown_without_leaks() -> None:
    """Cyclic heartbeat and encoder frames arrive on their own; an RTR request is answered;
    the emulator runs in a process of its own (no thread here); shutdown ends it."""
    db: Any = official_dbc()
    frame_id = {name: db.get_message_by_name(f"Axis{NODE}_{name}").frame_id
                for name in ("Heartbeat", "Get_Encoder_Estimates", "Get_Bus_Voltage_Current")}
    before = set(threading.enumerate())
    bus = can.Bus(interface="dobhil", channel="demo")
    try:
        assert isinstance(bus, DobhilBus)
        assert "odrive" in bus.channel_info and "demo.yaml" in bus.channel_info
        assert set(threading.enumerate()) == before and bus.emulator.running
        seen: dict[int, can.Message] = {}
        end = time.monotonic() + BOUND
        while frame_id["Heartbeat"] not in seen and time.monotonic() < end:   # every 100 ms
            msg = bus.recv(0.5)
            if msg is not None:
                seen[msg.arbitration_id] = msg
        hb_msg, enc_msg = seen[frame_id["Heartbeat"]], seen[frame_id["Get_Encoder_Estimates"]]
        hb = db.decode_message(hb_msg.arbitration_id, hb_msg.data, decode_choices=False)
        # IDLE; the only error an idle axis nobody feeds may show is the watchdog's (firmware runs
        # the watchdog in every state): WATCHDOG_TIMER_EXPIRED = 0x01000000 on 0.6
        assert hb["Axis_State"] == 1 and hb["Axis_Error"] & ~0x01000000 == 0
        assert hb_msg.channel == "demo" and hb_msg.is_rx and not hb_msg.is_extended_id
        est = db.decode_message(enc_msg.arbitration_id, enc_msg.data)
        assert est["Pos_Estimate"] * TURN == pytest.approx(-0.005, abs=1e-6)   # configs/demo.yaml

        request = frame_id["Get_Bus_Voltage_Current"]
        bus.set_filters([{"can_id": request, "can_mask": 0x7FF, "extended": False}])
        bus.send(can.Message(arbitration_id=request, is_extended_id=False, is_remote_frame=True))
        reply = bus.recv(BOUND)
        assert reply is not None and reply.arbitration_id == request and not reply.is_remote_frame
        assert db.decode_message(request, reply.data)["Bus_Voltage"] == pytest.approx(24.0)
    finally:
        bus.shutdown()
    assert set(threading.enumerate()) == before and not bus.emulator.running
    bus.shutdown()   # again: no-op
    with pytest.raises(can.CanOperationError):
        bus.send(can.Message(arbitration_id=1))


def test_overrides_config_path_and_bad_channels(tmp_path: Path) -> None:
    assert override_items("plant.inertia=0.1, loop.period=0.002") == ("plant.inertia=0.1", "loop.period=0.002")
    assert override_items({"plant.inertia": 0.1}) == ("plant.inertia=0.1",)
    with DobhilBus(str(REPO / "configs" / "demo.yaml"),
                   overrides="plant.inertia=0.1,plant.initial_position=-0.02") as bus:
        assert bus.config.plant.inertia == 0.1
        assert bus.plant.true_position == pytest.approx(-0.02)
    assert resolve_config("paper/fig2c").resolve() == (REPO / "configs" / "paper" / "fig2c.yaml").resolve()
    with pytest.raises(EmulatedBusError, match=r"config 'nope'.*shipped: cia402-demo, demo, "
                                               r"identify-contact, identify-free, mit-demo, moteus-demo, paper/fig2a"):
        can.Bus(interface="dobhil", channel="nope")
    with pytest.raises(can.CanInitializationError, match="missing.yaml"):
        can.Bus(interface="dobhil", channel=str(tmp_path / "missing.yaml"))
    with pytest.raises(EmulatedBusError, match="unknown config key 'plant.inertai'"):
        can.Bus(interface="dobhil", channel="demo", overrides=["plant.inertai=1"])


async def _drive_with_odrive_can(bus: can.BusABC, torque: float) -> dict[str, object]:
    """odrive-can's documented sequence: start, clear errors, torque mode, closed loop,
    torque commands (faster than the watchdog), then zero torque and an encoder request."""
    from odrive_can.odrive import ODriveCAN

    drv = ODriveCAN(axis_id=NODE, can_bus=bus)
    feedback: list[dict[str, float]] = []
    drv.feedback_callback = lambda msg, _drv: feedback.append(msg.data)
    await drv.start()   # returns after the first heartbeat
    try:
        drv.check_alive()
        drv.clear_errors()
        drv.set_controller_mode("TORQUE_CONTROL", "PASSTHROUGH")
        await drv.set_axis_state("CLOSED_LOOP_CONTROL")
        drv.check_errors()
        state = drv.axis_state
        for _ in range(20):
            drv.set_input_torque(torque)
            await asyncio.sleep(0.01)
        drv.set_input_torque(0.0)
        await asyncio.sleep(0.3)   # the last command applied, the frames before it read:
        #                            the velocity is constant from here (no friction)
        estimates = await drv.get_encoder_estimates()
        drv.set_input_torque(0.0)
        return {"state": state, "estimates": estimates, "feedback": feedback}
    finally:
        drv.stop()   # Set_Axis_State IDLE, joins its reader thread


def test_odrive_can_client_through_the_dobhil_interface(tmp_path: Path) -> None:
    """ODriveCAN enables the emulated axis (CLOSED_LOOP_CONTROL, no error), commands a
    torque and reads encoder estimates in turns that match the plant's truth."""
    pytest.importorskip("odrive_can")
    before = set(threading.enumerate())
    overrides = [f"drive.profile={relaxed_profile(tmp_path)}", "plant.viscous_friction=0",
                 "plant.initial_position=-1", "loop.position_min=-10"]
    bus = can.Bus(interface="dobhil", channel="demo", overrides=overrides)
    try:
        result = asyncio.run(_drive_with_odrive_can(bus, torque=0.5))
        plant = bus.plant
        assert result["state"] == "CLOSED_LOOP_CONTROL"
        assert plant.true_velocity > 0.0   # the torque reached the plant
        est = result["estimates"]
        assert isinstance(est, dict)
        assert est["Vel_Estimate"] * TURN == pytest.approx(plant.true_velocity, rel=1e-5)
        assert est["Pos_Estimate"] * TURN > -1.0
        feedback = result["feedback"]
        assert isinstance(feedback, list) and len(feedback) > 10   # cyclic estimates every 10 ms
        assert feedback[0]["Pos_Estimate"] * TURN == pytest.approx(-1.0, abs=1e-6)
        emulator: Any = bus.emulator   # an EmulatedODrive
        assert wait_until(lambda: emulator.protocol_state == 1)   # IDLE after drv.stop()
        assert not emulator.watchdog_tripped
    finally:
        bus.shutdown()
    assert {t for t in threading.enumerate() if t.is_alive()} <= before


def test_a_bus_that_cannot_start_leaves_nothing_running(monkeypatch: pytest.MonkeyPatch) -> None:
    from dobhil.emulator.process import EmulatorProcess

    def refuse(self: EmulatorProcess, child_end: object) -> None:
        raise RuntimeError("emulator refused to start")

    before = set(threading.enumerate())
    monkeypatch.setattr(EmulatorProcess, "_start", refuse)
    with pytest.raises(RuntimeError, match="refused"):
        can.Bus(interface="dobhil", channel="demo")
    assert set(threading.enumerate()) == before   # and the conftest: no bus left open


#: a program that opens the dobhil bus, takes a frame, says so, then ends (normally, or by
#: an exception) without shutdown()
PROGRAM = """
import sys, can
bus = can.Bus(interface="dobhil", channel="demo")
assert bus.recv(5.0) is not None
print(getattr(bus.emulator, "pid", 0), flush=True)
if sys.argv[1] == "sleep":   # the killed program's fork server must end with it too
    from dobhil import forkserver
    print(" ".join(str(p) for p in forkserver.server_pids()), flush=True)
if sys.argv[1] == "raise":
    raise RuntimeError("the program failed")
if sys.argv[1] == "sleep":
    import time
    time.sleep(60)
"""


@pytest.mark.parametrize("how", ["return", "raise"])
def test_a_program_that_never_shuts_the_bus_down_still_ends(tmp_path: Path, how: str) -> None:
    """python-can must not keep the interpreter alive: no thread holds it, and the
    emulator's process ends with the program (it reads the end of its socket)."""
    import os
    import select
    import subprocess
    import sys

    script = tmp_path / "no_shutdown.py"   # a plain script: no __main__ guard
    script.write_text(PROGRAM, encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script), how], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60)   # a bound against a hang
        assert ready, "the program did not open the bus"
        line = proc.stdout.readline()   # the bus is open and a frame came
        assert line.strip().isdigit(), (line, proc.stderr.read() if proc.stderr else "")
        child = int(line)
        start = time.monotonic()
        try:
            code = proc.wait(timeout=10)   # a bound against a hang; the 2 s is checked below
        except subprocess.TimeoutExpired:
            code = None
        ended = time.monotonic() - start
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = proc.stderr.read() if proc.stderr else ""
    assert code is not None and ended < 2.0, f"the program took {ended:.2f} s to end after its last statement"
    assert code == (0 if how == "return" else 1), err
    if how == "raise":
        assert "RuntimeError: the program failed" in err
    assert wait_until(lambda: not _alive(child)), "the emulator's process outlived the program"
    assert os.getpid() != child


def _alive(pid: int) -> bool:
    import os
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:   # a zombie child of the (ended) program is reaped by init: gone for good soon
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return True


def test_the_emulator_dies_with_a_killed_program(tmp_path: Path) -> None:
    """No orphan: a program SIGKILLed with the bus open (no atexit, nothing closed by
    hand) takes the emulator's process with it -- it reads the end of its socket."""
    import select
    import signal
    import subprocess
    import sys

    script = tmp_path / "killed.py"
    script.write_text(PROGRAM, encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script), "sleep"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, cwd=tmp_path)
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        assert ready, "the program did not open the bus"
        child = int(proc.stdout.readline())
        servers = [int(p) for p in proc.stdout.readline().split()]
        assert servers, "no fork server started the emulated drive"
        assert _alive(child) and all(_alive(p) for p in servers)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        assert wait_until(lambda: not _alive(child)), "the emulator's process outlived its program"
        # the fork server that forked it reads the end of its control socket and exits
        assert wait_until(lambda: not any(_alive(p) for p in servers)), "a fork server outlived it"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
