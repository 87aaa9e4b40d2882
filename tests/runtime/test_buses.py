"""Opening a bus: python-can's own warnings become part of dobhil's one error line."""

from __future__ import annotations

import logging
import subprocess
import sys
from typing import Any

import can
import pytest

from dobhil.errors import BusError
from dobhil.runtime import buses
from dobhil.runtime.buses import BusSpec, open_bus


def test_warnings_logged_while_opening_are_folded_into_the_error(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """As python-can's kvaser backend does: a warning on import, then an obscure error."""
    def failing_bus(**kwargs: Any) -> can.BusABC:
        logging.getLogger("can.kvaser").warning("Kvaser canlib is unavailable.")
        raise NameError("name 'canGetNumberOfChannels' is not defined")

    monkeypatch.setattr(buses.can, "Bus", failing_bus)
    with pytest.raises(BusError) as info:
        open_bus(BusSpec("kvaser", "0"))
    text = str(info.value)
    assert "canGetNumberOfChannels" in text and "Kvaser canlib is unavailable" in text and "libcanlib" in text
    assert "\n" not in text
    assert capsys.readouterr().err == ""  # nothing printed above our line
    assert not any(isinstance(h, buses._CaughtWarnings) for h in logging.getLogger().handlers)


def test_a_missing_library_gets_an_install_hint(monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    def failing_bus(**kwargs: Any) -> can.BusABC:
        logging.getLogger("can.pcan").warning("uptime library not available, timestamps are relative to boot time")
        raise OSError("pcanbasic library not found.")

    monkeypatch.setattr(buses.can, "Bus", failing_bus)
    with pytest.raises(BusError, match=r"pcanbasic library not found \(install PEAK-System's PCAN-Basic") as info:
        open_bus(BusSpec("pcan", "PCAN_USBBUS1"))
    assert "uptime" not in str(info.value)  # the error says it all; a side remark is dropped
    assert capsys.readouterr().err == ""


def test_the_command_prints_one_line_for_an_interface_without_its_library() -> None:
    """Through a fresh interpreter (the warnings come once, on the interface's first import)."""
    done = subprocess.run([sys.executable, "-m", "dobhil", "run", "demo", "--bus", "serial:/dev/nonexistent-tty"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "serial:/dev/nonexistent-tty" in done.stderr


def test_warnings_of_a_bus_that_opens_are_still_shown(monkeypatch: pytest.MonkeyPatch,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    """As python-can's pcan backend does when it opens without the uptime library: the
    warning (timestamps relative to boot) matters to the run, so it is not swallowed."""
    real_bus = can.Bus

    def opening_bus(**kwargs: Any) -> can.BusABC:
        logging.getLogger("can.pcan").warning("uptime library not available, timestamps are relative to boot")
        return real_bus(interface="virtual", channel="warned")

    monkeypatch.setattr(buses.can, "Bus", opening_bus)
    with caplog.at_level(logging.WARNING, logger="can"):
        bus = open_bus(BusSpec("pcan", "PCAN_USBBUS1"))
    bus.shutdown()
    assert [r.getMessage() for r in caplog.records if r.name == "can"] == [
        "uptime library not available, timestamps are relative to boot"]
