"""dobhil enables against odrive-can's own mock (``odrive_can.mock.ODriveCANMock``), an
independent ODrive peer that decodes every frame with cantools and the official 0.6.10
DBC: a Set_Axis_State sent with DLC 4 (not the DBC's 8) raises inside its
cantools decode and is dropped, so the axis never reached CLOSED_LOOP_CONTROL.

The mock runs its asyncio tasks on a thread of its own (heartbeat every 0.2 s, 0.5 s
to change state), on a private python-can ``virtual`` channel. It answers any RTR with
zeros (a heartbeat in state UNDEFINED) and ignores torque setpoints, so only the enable
handshake and the disable are checked here, not torque control.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import threading
import time
from collections.abc import Iterator

import can
import pytest

from dobhil.drives import DriveState, load_profile, make_drive

mock_module = pytest.importorskip("odrive_can.mock")

_CHANNELS = itertools.count()
NODE = 3


class MockThread:
    """ODriveCANMock on its own event loop thread; :meth:`stop` cancels and joins it."""

    def __init__(self, bus: can.BusABC) -> None:
        self.loop = asyncio.new_event_loop()
        self.mock = mock_module.ODriveCANMock(axis_id=NODE, can_bus=bus)
        self.task: asyncio.Task[None] | None = None
        self.thread = threading.Thread(target=self._run, name="odrive-can-mock", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.task = self.loop.create_task(self.mock.main())
        try:
            self.loop.run_until_complete(self.task)
        except BaseException:  # cancelled by stop()
            pass
        finally:
            self.loop.close()

    def axis_state(self) -> str:
        return str(self.mock.odrive.axis_state)

    def stop(self) -> None:
        while self.task is None and self.thread.is_alive():
            time.sleep(0.01)
        if self.task is not None:
            self.loop.call_soon_threadsafe(self.task.cancel)
        self.thread.join(5.0)
        self.mock.notifier.stop()


@pytest.fixture
def mock_bus() -> Iterator[tuple[can.BusABC, MockThread]]:
    channel = f"odrive-can-mock-{next(_CHANNELS)}"
    mock_side = can.Bus(interface="virtual", channel=channel)
    host = can.Bus(interface="virtual", channel=channel)
    mock = MockThread(mock_side)
    try:
        yield host, mock
    finally:
        mock.stop()
        mock_side.shutdown()
        host.shutdown()


def test_dobhil_enables_and_disables_the_odrive_can_mock(mock_bus: tuple[can.BusABC, MockThread]) -> None:
    host, mock = mock_bus
    profile = dataclasses.replace(load_profile("odrive-0.6"), bus={}, node_id=NODE, enable_timeout=5.0)
    drive = make_drive(host, profile)
    drive.enable()
    assert drive.status.state is DriveState.ENABLED
    assert mock.axis_state() == "CLOSED_LOOP_CONTROL"
    assert mock.mock.odrive.control_mode == "TORQUE_CONTROL"
    assert drive.disable() is True
    deadline = time.monotonic() + 5.0
    while mock.axis_state() != "IDLE" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert mock.axis_state() == "IDLE"
