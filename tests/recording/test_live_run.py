"""``dobhil run --live``: a WebSocket client connected during a lockstep run receives its messages."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
from live_client import LiveClient, counts_at_least

from dobhil.cli.main import main
from dobhil.recording.cycles import unfold
from dobhil.recording.reader import decoder_for, open_log
from dobhil.recording.schemas import SPECS_BY_NAME, Topic

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "configs" / "demo.yaml"


def test_a_client_receives_controller_and_can_rx_during_a_lockstep_run(tmp_path: Path) -> None:
    """The default (cycle) layout: the live view gets the file's ``/cycle`` messages, each
    holding the cycle's ``/controller`` and the frames received after it, in order."""
    path = tmp_path / "live.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "dobhil", "run", str(DEMO), "--emulate", "--lockstep",
                             "--duration", "600", "--log", str(path), "--live", "127.0.0.1:0"],
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert line.startswith("live view: ws://127.0.0.1:"), line + proc.stderr.read()
        with LiveClient(line.split()[-1]) as client:
            client.subscribe(["/cycle"])
            received = client.collect(counts_at_least({"/cycle": 50}), timeout=60)
            advertised = dict(client.advertised)
        assert proc.poll() is None  # received during the run
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "stopped: signal" in out, err
    assert (advertised["/cycle"]["encoding"], advertised["/cycle"]["schemaName"]) == ("protobuf", "dobhil.Cycle")
    controller = decoder_for("protobuf", SPECS_BY_NAME["/controller"], "live", "/controller")
    held = [list(unfold(r.payload, r.log_time_ns)) for r in received if r.topic == "/cycle"]
    cycles = [controller(data)["cycle"] for parts in held for topic, _, data in parts if topic is Topic.CONTROLLER]
    assert len(cycles) == len(held) >= 50 and cycles == sorted(cycles)  # one a message, in order
    assert sum(topic is Topic.CAN_RX for parts in held for topic, _, _ in parts) >= 50   # the frames with them
    recorded = open_log(path).info()
    assert recorded.stop_reason == "signal" and recorded.metadata["recording"]["live_dropped"] == "0"


def test_live_needs_a_log_and_a_valid_address(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.1"]
    for extra, words in ((["--live", "8765"], "--live needs a log"),
                         (["--live", "host:port", "--log", str(tmp_path / "a.mcap")], "port")):
        capsys.readouterr()
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("where", ["busy", "unknown host"])
def test_live_that_cannot_listen_leaves_no_log_and_the_rerun_works(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str) -> None:
    """The address is checked before the log is opened: a refused --live leaves no stub
    (which would block the rerun with the same --log)."""
    import socket
    path = tmp_path / "a.mcap"
    base = ["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.05", "--log", str(path)]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        live = f"127.0.0.1:{taken.getsockname()[1]}" if where == "busy" else "no-such-host.invalid:8799"
        capsys.readouterr()
        assert main([*base, "--live", live]) == 2
        err = capsys.readouterr().err
    assert err.count("\n") == 1 and ("in use" in err if where == "busy" else "not known" in err), err
    assert not list(tmp_path.iterdir())
    assert main(base) == 0 and path.is_file()


@pytest.mark.parametrize("config", ["demo.yaml", "two-axis-demo.yaml"])
def test_the_live_view_line_of_an_ipv6_host_is_a_url(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     config: str) -> None:
    """``--live [::1]:0`` prints ``ws://[::1]:PORT``, the host in brackets as in a URL (RFC 3986
    section 3.2.2), for one axis and several: the line is what a user pastes into Foxglove."""
    from urllib.parse import urlsplit
    capsys.readouterr()
    assert main(["run", str(ROOT / "configs" / config), "--emulate", "--lockstep", "--duration", "0.05",
                 "--log", str(tmp_path / "a.mcap"), "--live", "[::1]:0"]) == 0
    line = next(x for x in capsys.readouterr().err.splitlines() if x.startswith("live view:"))
    url = urlsplit(line.split()[-1])
    assert url.scheme == "ws" and url.hostname == "::1" and url.port, line


def test_live_on_loopback_prints_no_exposure_warning(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.cli.recording import live_address
    capsys.readouterr()
    view = live_address("127.0.0.2:0", tmp_path / "a.mcap")
    assert view is not None and (view.host, view.port) == ("127.0.0.2", 0)
    assert capsys.readouterr().err == ""


def test_live_beyond_loopback_warns_once_it_listens_and_a_refused_run_does_not(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """The warning, without binding a public interface (the bind check is stubbed, the
    listening view is a stand-in): one line before the URL, naming the port the view got;
    a run refused after the address check (its --log exists) says only why, in one line,
    and warns of nothing it never showed."""
    from types import SimpleNamespace

    import dobhil.live.address as address
    from dobhil.cli.recording import _say_live
    from dobhil.live import LiveServer
    from dobhil.recording.writer import LiveView
    monkeypatch.setattr(address, "check_bindable", lambda _address: None)
    existing = tmp_path / "a.mcap"
    existing.write_bytes(b"recorded")
    capsys.readouterr()
    for config in ("demo.yaml", "two-axis-demo.yaml"):
        assert main(["run", str(ROOT / "configs" / config), "--emulate", "--lockstep", "--duration", "0.05",
                     "--log", str(existing), "--live", "0.0.0.0:8799"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--log" in err and "warning" not in err, err
    assert existing.read_bytes() == b"recorded"
    _say_live(SimpleNamespace(live=LiveView(LiveServer, "0.0.0.0", 0), live_port=8799))  # type: ignore[arg-type]
    warning, url = capsys.readouterr().err.splitlines()
    assert warning.startswith("warning: the live view on 0.0.0.0:8799 (every network interface)")
    assert "anyone" in warning and "read-only" in warning and url == "live view: ws://0.0.0.0:8799"


def test_a_port_taken_after_the_check_still_leaves_no_log(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The race the early check cannot close (the port taken between the check and the
    writer's server): the writer never gets ready, and the header-only file is removed."""
    import socket

    import dobhil.live.address as address
    monkeypatch.setattr(address, "check_bindable", lambda _address: None)  # as if taken after the check
    path = tmp_path / "a.mcap"
    base = ["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.05", "--log", str(path)]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        capsys.readouterr()
        assert main([*base, "--live", f"127.0.0.1:{taken.getsockname()[1]}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot listen" in err, err
    assert not list(tmp_path.iterdir())
    assert main(base) == 0 and path.is_file()


def test_a_client_receives_every_axis_and_the_shared_bus_of_a_several_axis_run(tmp_path: Path) -> None:
    """``dobhil run AXES.yaml --log --live``: the live view serves each axis' topics and its
    bus' frames while the loop runs; SIGINT stops both axes and the log is complete."""
    path = tmp_path / "axes-live.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "dobhil", "run", str(ROOT / "configs" / "two-axis-demo.yaml"),
                             "--emulate", "--duration", "600", "--log", str(path), "--live", "127.0.0.1:0"],
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    wanted = {"/axis/left/cycle": 50, "/axis/right/cycle": 50, "/bus/socketcan_can0/can/rx": 50}
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert line.startswith("live view: ws://127.0.0.1:"), line + proc.stderr.read()
        with LiveClient(line.split()[-1]) as client:
            client.subscribe(list(wanted))
            received = client.collect(counts_at_least(wanted), timeout=60)
        assert proc.poll() is None  # received during the run
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "stopped: signal" in out, err
    assert {r.topic for r in received} >= set(wanted)
    recorded = open_log(path).info()
    assert recorded.stop_reason == "signal" and recorded.metadata["recording"]["live_dropped"] == "0"


def test_demo_live_waits_for_a_client_and_plays_it_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """``dobhil demo --live``: a lockstep demo lasts a fraction of a second, over before anyone
    can open Foxglove (it was: the live view listened for 0.1 s and the demo ended). It runs,
    then plays its log at the recorded pace once a client subscribes, as ``log serve`` does."""
    import socket
    import threading
    import time

    from websockets.exceptions import InvalidHandshake

    from dobhil.live import cli as live_cli
    monkeypatch.setattr(live_cli, "_SETTLE_S", 0.0)  # the client subscribes one topic
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    got: list[object] = []

    def watch() -> None:  # a person opening Foxglove some time after the demo started
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                with LiveClient(f"ws://127.0.0.1:{port}", open_timeout=2) as client:
                    client.subscribe(["/cycle"])   # the default layout's one message per cycle
                    got.extend(client.collect(counts_at_least({"/cycle": 50}), timeout=20))
                    return
            except (OSError, InvalidHandshake):  # not listening yet, or the address check's probe
                time.sleep(0.05)

    client = threading.Thread(target=watch, daemon=True)
    client.start()
    log = tmp_path / "demo.mcap"
    code = main(["demo", "--out", str(tmp_path), "--log", str(log), "--set", "loop.duration=0.1",
                 "--live", f"127.0.0.1:{port}"])
    client.join(5)
    out = capsys.readouterr().out
    assert code == 0, out
    assert len(got) >= 50, out
    assert f"serving {log} on ws://127.0.0.1:{port}" in out and "waiting for a client" in out


def test_demo_live_stopped_by_ctrl_c_does_not_wait_for_a_client(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C during the demo's run stops the demo: its log (stop reason ``signal``) is not
    then played to a client it would wait for (a second Ctrl-C); any other end is."""
    import dobhil.live.cli as live_cli
    from dobhil.cli.demo_cmd import _play_live
    from dobhil.recording.writer import LogWriter
    served: list[Path] = []
    monkeypatch.setattr(live_cli, "serve_command", lambda path, **_: served.append(path))
    for reason in ("signal", "unstable", "done"):
        log = tmp_path / f"{reason}.mcap"
        LogWriter(open(log, "wb"), metadata={}, fsync=False).finish(reason)
        _play_live(log, "127.0.0.1:0")
    assert served == [tmp_path / "unstable.mcap", tmp_path / "done.mcap"]
