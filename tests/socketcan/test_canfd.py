"""CAN FD on vcan (``mtu 72``): a python-can FD bus opens, FD frames from ``cansend`` and from
python-can reach dobhil's recorder -- a run's (its drive profile's ``bus: {fd: true}``) and
python-can's ``can.Logger`` with dobhil's MCAP writer plugin -- and ``dobhil log export
--can`` to candump, ASC and BLF keeps the FD flag, the bit rate switch, the error state
indicator, the length and every byte, as the kernel carried them (``candump -l``)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import can

from dobhil.drives.odrive.codec import AxisState

from .guest import CONFIGS, Dobhil, guest_overlay, summary_json
from .peers import crashes_say_where  # noqa: F401 (an autouse fixture: applies here)
from .peers import candump_log, cansend, cli, heartbeat_state, own_bus, read_run, start_candump, watch

#: (cansend's frame text) -- FD with BRS and 64 bytes, FD with 12 bytes (DLC 9) and no
#: BRS, an extended FD frame with BRS and ESI (flags 3), and a classic frame among them
CANSEND = ("123##1" + bytes(range(64)).hex(), "124##0" + bytes(range(100, 112)).hex(),
           "1ABCDEF0##3" + bytes(range(200, 248)).hex(), "127#1122334455667788")
#: sent by python-can from the test's own FD bus
PYTHON_CAN = (can.Message(arbitration_id=0x125, is_extended_id=False, is_fd=True, bitrate_switch=True,
                          data=bytes(range(255, 191, -1))),
              can.Message(arbitration_id=0x126, is_extended_id=False, is_fd=True, bitrate_switch=False,
                          data=bytes(20)))
IDS = {0x123, 0x124, 0x1ABCDEF0, 0x127, 0x125, 0x126}

Frame = tuple[int, bool, bool, bool, bool, int, bytes]


def _key(msg: can.Message) -> Frame:
    """What must survive: id, 29-bit, FD, BRS, ESI, length, bytes."""
    return (msg.arbitration_id, msg.is_extended_id, msg.is_fd, msg.bitrate_switch, msg.error_state_indicator,
            len(msg.data), bytes(msg.data))


def _ours(messages: list[can.Message]) -> list[Frame]:
    return sorted(_key(m) for m in messages if m.arbitration_id in IDS and not m.is_error_frame)


def _mtu_72(iface: str) -> None:
    """vcan's MTU set to CANFD_MTU (72) explicitly, and read back."""
    for args in (["down"], ["mtu", "72"], ["up"]):
        out = subprocess.run(["ip", "link", "set", "dev", iface, *args], capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
    shown = subprocess.run(["ip", "-details", "link", "show", "dev", iface], capture_output=True, text=True).stdout
    assert " mtu 72 " in shown, shown


def test_fd_frames_reach_the_recorders_and_every_export(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    _mtu_72(vcan)
    config = CONFIGS / "demo.yaml"
    overlay = guest_overlay(tmp_path, "odrive", extra={"loop.duration": 5.0}, profile={"bus.fd": True})
    emulator = dobhil.emulate(config, vcan, overlay)
    dump = start_candump(dobhil, vcan)
    log, plugin = tmp_path / "run.mcap", tmp_path / "plugin.mcap"
    with own_bus(vcan, fd=True) as bus, own_bus(vcan, fd=True) as logged:
        notifier = can.Notifier(logged, [can.Logger(str(plugin))])   # dobhil's writer plugin (.mcap)
        run = dobhil.start("run", ["run", str(config), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay),
                                   "--log", str(log), "--summary-json"])
        watch(bus, lambda m: heartbeat_state(m, 3) == AxisState.CLOSED_LOOP_CONTROL)   # the loop runs
        for text in CANSEND:
            cansend(vcan, text)
        for msg in PYTHON_CAN:
            bus.send(msg)
        run.wait()
        notifier.stop()   # stops the listeners too: the plugin's file is finished
    dump.stop()
    emulator.stop()
    assert run.returncode == 0 and summary_json(run)["stop_reason"] == "done", run.text()

    kernel = _ours(list(can.LogReader(str(candump_log(dobhil)))))
    assert len(kernel) == len(CANSEND) + len(PYTHON_CAN), kernel
    assert sum(f[2] for f in kernel) == 5 and {f[5] for f in kernel} == {8, 12, 20, 48, 64}
    # the run records what it received on /can/rx; python-can's logger files a frame by its
    # is_rx, which SocketCAN sets False for every frame made on this host (MSG_DONTROUTE,
    # can/interfaces/socketcan/socketcan.py) -- on vcan, all of them: its MCAP has them on /can/tx
    for name, path in (("run", log), ("can.Logger", plugin)):
        rec = read_run(path, ("/can/rx", "/can/tx"))
        assert _ours(rec.frames("/can/rx") + rec.frames("/can/tx")) == kernel, name
        for fmt, suffix in (("candump", ".log"), ("asc", ".asc"), ("blf", ".blf")):
            out = tmp_path / f"{path.stem}-export{suffix}"
            cli(["log", "export", str(path), "--can", "--format", fmt, "-o", str(out)])
            extra = {"relative_timestamp": False} if suffix == ".asc" else {}
            assert _ours(list(can.LogReader(str(out), **extra))) == kernel, (name, fmt)
