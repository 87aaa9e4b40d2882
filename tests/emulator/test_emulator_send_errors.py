"""An emulated drive whose sends fail: a refused frame (ENOBUFS, the transmit queue full) is
counted and the drive goes on; an interface that is down or gone ends it, also when only its
sends can tell (Linux hands a socket's pending ENETDOWN to whichever of send and receive comes
first: an emulator that sent first never sees it on a receive).

``dobhil emulate`` says both in its last line. The faults are
:class:`dobhil.emulator.bus_faults.RefuseSend` with the errno SocketCAN gives."""

from __future__ import annotations

import errno
import itertools
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest

from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.drives import load_profile
from dobhil.drives.odrive import codec as odrive
from dobhil.drives.odrive.codec import CmdId06, Firmware
from dobhil.emulator.bus_faults import RefuseSend
from dobhil.emulator.faults import FaultyBus
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant
from dobhil.errors import BusError
from dobhil.runtime import buses
from dobhil.runtime.buses import BusSpec


DEMO = Path(__file__).resolve().parents[2] / "configs" / "demo.yaml"
_CHANNELS = itertools.count()
#: the emulator's frames refused before the interface takes them again
REFUSED = 5


def _faulty_bus(refuse: RefuseSend) -> FaultyBus:
    channel = f"send-errors-{next(_CHANNELS)}"
    return FaultyBus(can.Bus(interface="virtual", channel=channel), [refuse], owns_inner=True)


@pytest.fixture
def emulator_on() -> Iterator[list[EmulatedODrive]]:
    """Emulated ODrives made by the test, closed at its end."""
    made: list[EmulatedODrive] = []
    yield made
    for emu in made:
        try:
            emu.close()
        except BusError:
            pass  # the test looked at it already


def _start(made: list[EmulatedODrive], refuse: RefuseSend) -> EmulatedODrive:
    emu = EmulatedODrive(_faulty_bus(refuse), load_profile("odrive-0.6"), Plant.from_config(load_config(DEMO)))
    made.append(emu)
    emu.start()
    return emu


def _wait(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + 30.0   # a bound for a loaded machine, not a measurement
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def test_refused_sends_are_counted_and_the_drive_goes_on(emulator_on: list[EmulatedODrive]) -> None:
    refuse = RefuseSend(at=10, count=REFUSED)
    emu = _start(emulator_on, refuse)
    _wait(lambda: emu.frames_sent > 10 + REFUSED, "the emulator sent nothing after the refusals")
    assert emu.alive
    assert emu.send_errors == refuse.applied == REFUSED
    emu.stop()   # raises what the thread raised: nothing


@pytest.mark.parametrize("code", [errno.ENETDOWN, errno.ENODEV, errno.ENXIO])
def test_a_send_on_an_interface_down_or_gone_ends_the_emulator(code: int,
                                                               emulator_on: list[EmulatedODrive]) -> None:
    """Only the sends fail (the receive never hears of it): the thread ends all the same,
    and ``stop`` raises the BusError in the interface's words."""
    emu = _start(emulator_on, RefuseSend(at=10, code=code))
    _wait(lambda: not emu.alive, "the emulator went on sending into an interface that is gone")
    assert emu.send_errors == 0
    with pytest.raises(BusError, match=f"send failed: .*{os.strerror(code)}"):
        emu.stop()


def _emulate_on(monkeypatch: pytest.MonkeyPatch, refuse: RefuseSend) -> None:
    """``dobhil emulate`` opens a bus whose sends meet ``refuse``."""
    monkeypatch.setattr(buses, "open_bus", lambda spec: _faulty_bus(refuse))


def test_dobhil_emulate_reports_the_refused_sends(monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    _emulate_on(monkeypatch, RefuseSend(at=10, count=REFUSED))
    code = main(["emulate", str(DEMO), "--bus", "virtual:unused", "--duration", "0.5"])
    out = capsys.readouterr().out
    assert code == 0
    assert out.splitlines()[-1].endswith(f" sent, {REFUSED} refused by the bus"), out


def test_dobhil_emulate_ends_when_its_interface_goes_down(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    _emulate_on(monkeypatch, RefuseSend(at=10, code=errno.ENETDOWN))
    code = main(["emulate", str(DEMO), "--bus", "virtual:unused", "--duration", "60"])
    captured = capsys.readouterr()
    assert code == 1
    line = captured.err.strip()
    assert "\n" not in line and line.startswith("dobhil emulate: stopped: bus virtual:unused lost ("), line
    assert "Network is down" in line, line
    assert BusSpec.parse("virtual:unused").describe() in line


def test_an_answer_into_an_interface_that_is_down_ends_the_emulator() -> None:
    """The interface goes down while the drive answers a request (Linux hands the pending
    ENETDOWN to that send, so no receive will ever report it): the answer's BusError ends
    the drive, rather than being counted as a frame the drive could not handle."""
    channel = f"send-errors-{next(_CHANNELS)}"
    reply = odrive.arbitration_id(3, CmdId06.GET_VERSION)
    bus = FaultyBus(can.Bus(interface="virtual", channel=channel), [RefuseSend(at=0, code=errno.ENETDOWN,
                                                                              ids={reply})], owns_inner=True)
    host = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedODrive(bus, load_profile("odrive-0.6"), Plant.from_config(load_config(DEMO)))
    try:
        host.send(odrive.encode(odrive.Request(CmdId06.GET_VERSION), node_id=3, firmware=Firmware.V0_6))
        with pytest.raises(BusError, match="send failed: .*Network is down"):
            emu.handle_pending()
        assert emu.frame_errors == 0
    finally:
        host.shutdown()
        emu.close()
