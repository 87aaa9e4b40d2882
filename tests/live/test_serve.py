"""``dobhil log serve``: a recorded lockstep run reaches a WebSocket client as recorded."""

from __future__ import annotations

import base64

import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import jsonschema
import pytest
from dobhil_forks import DobhilForks, Done
from live_client import LiveClient, counts_at_least
from mcap.reader import make_reader
from websockets.exceptions import ConnectionClosed, InvalidHandshake

from dobhil.canio.mcap_writer import McapWriter
from dobhil.recording.encodings import encoding
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import SPECS_BY_NAME

REPO = Path(__file__).resolve().parents[2]
TOPICS = ("/controller", "/can/rx")


def _dobhil(forks: DobhilForks, *args: str, timeout: float = 180) -> Done:
    """``dobhil ARGS`` run to its end as a process (forked: tests/dobhil_forks.py)."""
    return forks.run(list(args), Path.cwd(), timeout=timeout)


def _record(forks: DobhilForks, path: Path, *layout: str) -> Path:
    """A 0.5 s lockstep demo run logged to ``path`` (``layout``: ``--log-layout ...`` or none)."""
    proc = _dobhil(forks, "run", str(REPO / "configs" / "demo.yaml"), "--emulate", "--lockstep",
                   "--duration", "0.5", "--log", str(path), *layout)
    assert proc.returncode == 0, proc.stderr
    return path


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory, dobhil_forks: DobhilForks) -> Path:
    """A log in the topics layout: a message per topic, each served as its own."""
    return _record(dobhil_forks, tmp_path_factory.mktemp("serve") / "run.mcap", "--log-layout", "topics")


def _recorded_messages(path: Path, topic: str) -> list[tuple[int, bytes]]:
    with open(path, "rb") as f:
        return [(m.log_time, m.data) for _, _, m in make_reader(f).iter_messages(topics=[topic])]


def _recorded_schemas(path: Path) -> dict[str, tuple[str, bytes]]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {c.topic: (summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].data)
            for c in summary.channels.values()}


def _serve(path: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "dobhil", "log", "serve", str(path), "--live", "127.0.0.1:0", "--speed", "0.25"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def test_a_log_in_the_default_cycle_layout_is_served_as_recorded(tmp_path: Path, dobhil_forks: DobhilForks) -> None:
    """A log in the default layout (cycle): its own channels advertised with their schemas,
    each ``/cycle`` message (what Foxglove decodes by ``dobhil.Cycle``) delivered as recorded."""
    path = _record(dobhil_forks, tmp_path / "run.mcap")
    assert open_log(path).layout == "cycle"
    expected = _recorded_messages(path, "/cycle")
    schemas = _recorded_schemas(path)
    serving = _serve(path)
    try:
        assert serving.stdout is not None
        url = serving.stdout.readline().split(" on ", 1)[1].split()[0]
        with LiveClient(url) as client:
            client.subscribe(["/cycle"])
            received = client.collect(counts_at_least({"/cycle": len(expected)}), timeout=120)
            advertised = dict(client.advertised)
        out, err = serving.communicate(timeout=60)
    finally:
        if serving.poll() is None:
            serving.kill()
            serving.communicate(timeout=30)
    assert serving.returncode == 0, err
    assert {t: (c["schemaName"], base64.b64decode(c["schema"])) for t, c in advertised.items()} == schemas
    assert [(r.log_time_ns, r.payload) for r in received if r.topic == "/cycle"] == expected
    assert "dropped 0" in out.strip().splitlines()[-1], out


@pytest.fixture
def serving(recorded: Path) -> Iterator[subprocess.Popen[str]]:
    proc = _serve(recorded)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)


def test_serve_delivers_recorded_topics_byte_for_byte(recorded: Path, serving: subprocess.Popen[str]) -> None:
    assert serving.stdout is not None
    first = serving.stdout.readline()
    assert first.startswith(f"serving {recorded} on ws://127.0.0.1:"), first
    url = first.split(" on ", 1)[1].split()[0]
    expected = {t: _recorded_messages(recorded, t) for t in TOPICS}
    assert all(expected.values())
    schemas = _recorded_schemas(recorded)
    with LiveClient(url) as client:
        client.subscribe(TOPICS)
        received = client.collect(counts_at_least({t: len(expected[t]) for t in TOPICS}), timeout=120)
        advertised = dict(client.advertised)
    out, err = serving.communicate(timeout=60)
    assert serving.returncode == 0, err
    assert set(advertised) == set(schemas)  # every recorded topic, no other
    for topic, channel in advertised.items():
        # the WebSocket protocol carries a binary (protobuf) schema in base64
        assert (channel["schemaName"], base64.b64decode(channel["schema"])) == schemas[topic]
        assert (channel["encoding"], channel["schemaEncoding"]) == ("protobuf", "protobuf")
    for topic in TOPICS:
        got = [(r.log_time_ns, r.payload) for r in received if r.topic == topic]
        assert got == expected[topic]
        spec = SPECS_BY_NAME[topic]   # each payload the protobuf message of the documented fields
        decode = encoding("protobuf").decoder(spec)
        for _, payload in got[:50]:
            jsonschema.validate(decode(payload), spec.json_schema())
    assert "dropped 0" in out.strip().splitlines()[-1], out


@pytest.mark.parametrize(
    ("args", "what"),
    [
        (["missing.mcap"], "no such file"),
        (["not.mcap"], "not an MCAP file"),
        (["RUN", "--speed", "0"], "--speed"),
        (["RUN", "--speed", "nan"], "--speed"),
        (["RUN", "--speed", "1e-300"], "from 0.001 to 1e+06"),  # would sleep past time.sleep's range
        (["RUN", "--speed", "1e300"], "from 0.001 to 1e+06"),
        (["RUN", "--live", "host:port"], "[HOST:]PORT"),
        (["RUN", "--live", "70000"], "out of range"),
        (["RUN", "--live", "no-such-host.invalid:8799"], "not known"),  # no exposure warning before it
        (["empty.mcap"], "no messages to serve"),  # refused before it listens, not once a client comes
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path: Path, recorded: Path, args: list[str], what: str,
                                      dobhil_forks: DobhilForks) -> None:
    (tmp_path / "not.mcap").write_text("hello")
    McapWriter(tmp_path / "empty.mcap").stop()  # a capture of no frame: channels, no message
    args = [str(recorded) if a == "RUN" else str(tmp_path / a) if a.endswith(".mcap") else a for a in args]
    live = [] if "--live" in args else ["--live", "127.0.0.1:0"]
    proc = _dobhil(dobhil_forks, "log", "serve", *args, *live)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert proc.stderr.count("\n") == 1 and what in proc.stderr and "Traceback" not in proc.stderr
    assert proc.stdout == ""


def test_truncated_file_is_one_line_exit_2(tmp_path: Path, recorded: Path, dobhil_forks: DobhilForks) -> None:
    cut = tmp_path / "cut.mcap"
    data = recorded.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    proc = _dobhil(dobhil_forks, "log", "serve", str(cut), "--live", "127.0.0.1:0")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "truncated" in proc.stderr, proc.stderr


def test_interrupt_while_waiting_for_a_client_stops_cleanly(recorded: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "dobhil", "log", "serve", str(recorded), "--live", "127.0.0.1:0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().split(" on ", 1)[1].split()[0]
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    with pytest.raises(OSError):  # nothing listens any more
        LiveClient(url, open_timeout=5)


def test_loop_starts_over_with_a_new_session(recorded: Path) -> None:
    expected = _recorded_messages(recorded, "/controller")
    proc = subprocess.Popen(
        [sys.executable, "-m", "dobhil", "log", "serve", str(recorded), "--live", "127.0.0.1:0", "--speed", "4",
         "--loop"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().split(" on ", 1)[1].split()[0]
        with LiveClient(url) as client:
            client.subscribe(["/controller"])
            first_session = client.server_info["sessionId"]
            # the second pass' serverInfo (its new session) comes before its messages
            received = client.collect(counts_at_least({"/controller": 2 * len(expected)}), timeout=120)
            new_session = client.server_info["sessionId"]
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130
    got = [(r.log_time_ns, r.payload) for r in received]
    assert got[: 2 * len(expected)] == expected + expected  # each pass as recorded
    assert new_session != first_session


def test_a_log_of_a_newer_dobhil_is_served_with_the_note_of_log_info(recorded: Path, tmp_path: Path,
                                                                      dobhil_forks: DobhilForks) -> None:
    """A recorded config with a key this version does not know (a newer dobhil's log) is no
    reason not to serve what was recorded: the messages go out as recorded and stderr has the
    note ``log info`` prints, once; bad input stays its one line, the note left out."""
    from tests.recording.test_logs_never_lie import rewrite_metadata
    newer = rewrite_metadata(recorded, tmp_path / "newer.mcap", "plant.magnet_force", "1")
    info = _dobhil(dobhil_forks, "log", "info", str(newer))
    assert info.returncode == 0, info.stderr
    note = next(line for line in info.stdout.splitlines() if line.startswith("note:")).removeprefix("note:").strip()
    assert "plant.magnet_force" in note
    bad = _dobhil(dobhil_forks, "log", "serve", str(newer), "--speed", "0", "--live", "127.0.0.1:0")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--speed" in bad.stderr, bad.stderr
    expected = _recorded_messages(recorded, "/controller")
    proc = subprocess.Popen(
        [sys.executable, "-m", "dobhil", "log", "serve", str(newer), "--live", "127.0.0.1:0", "--speed", "4"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert first.startswith(f"serving {newer} on ws://127.0.0.1:"), first
        with LiveClient(first.split(" on ", 1)[1].split()[0]) as client:
            client.subscribe(["/controller"])
            received = client.collect(counts_at_least({"/controller": len(expected)}), timeout=120)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert [(r.log_time_ns, r.payload) for r in received] == expected
    assert [line for line in err.splitlines() if "note" in line] == [f"dobhil log: note: {note}"], err


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _early_client(port: int, topic: str, out: list[object]) -> None:
    """What Foxglove does when it is left open on the address: connect as soon as something
    listens, subscribe to a topic the moment it is advertised, and watch until the server
    goes away. ``out`` gets the client's status messages (an error if it was refused), or
    the exception."""
    deadline = time.monotonic() + 20
    while True:
        try:
            client = LiveClient(f"ws://127.0.0.1:{port}", open_timeout=2)
            break
        # not listening yet, or check_bindable's probe: it listens and closes at once, and a
        # connection that reached it is refused in the handshake or reset before it (websockets
        # raises ConnectionClosedError then; seen once in a loaded run) -- Foxglove tries again
        except (OSError, InvalidHandshake, ConnectionClosed):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.001)
    try:
        with client:
            client.subscribe([topic])
            end = time.monotonic() + 5
            while time.monotonic() < end:
                client.collect(lambda _: False, timeout=end - time.monotonic())
    except (ConnectionClosed, TimeoutError):  # the server stopped (served), or still waits
        out.append([t for t in client.texts if t.get("op") == "status"])
    except Exception as exc:  # the test reports it
        out.append(exc)


def test_a_client_connected_before_the_channels_are_advertised_is_served(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """A Foxglove left open on the address connects the moment the server listens. foxglove-sdk
    (0.30.3) sends a channel added while a client is connected before it knows the channel as
    that client's: a subscription that comes back at once is refused ("Unknown channel ID"),
    the client believes itself subscribed and serve waited forever for it (seen 5 in 20 tries).
    The channels are advertised before the server listens: every try is served."""
    from dobhil.live import cli
    path = tmp_path / "frames.mcap"
    writer = McapWriter(path)
    for i in range(3):
        writer.on_message_received(can.Message(timestamp=1.0 + i * 1e-3, arbitration_id=0x10 + i, data=[i],
                                               is_rx=bool(i % 2)))
    writer.stop()
    monkeypatch.setattr(cli, "_GRACE_S", 0.0)   # what is received is not the point: whether serve ends
    monkeypatch.setattr(cli, "_SETTLE_S", 0.0)
    for _ in range(60):
        port, out = _free_port(), []
        client = threading.Thread(target=_early_client, args=(port, "/can/rx", out), daemon=True)
        client.start()
        served = threading.Thread(target=cli.serve_command, args=(path,),
                                  kwargs={"live": f"127.0.0.1:{port}", "speed": 1e6, "loop": False}, daemon=True)
        served.start()
        client.join(30)
        served.join(10)
        assert out == [[]], out   # no "Unknown channel ID" status, no error
        assert not served.is_alive(), "serve still waits for a subscriber"
    capsys.readouterr()


class _Passes(Exception):
    """Ends a looping playback after the passes a test wants."""


class _CountingServer:
    """What serve_recording needs of a LiveServer, on a clock that moves only when it sleeps."""

    def __init__(self, passes: int) -> None:
        self.topics: tuple[str, ...] = ()
        self.now, self.slept, self.passes, self.left = 0.0, 0.0, 1, passes

    def add_channel(self, topic: str, **_: object) -> None:
        self.topics += (topic,)

    def publish(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        self.now += 1e-6  # publishing takes a little time

    def new_session(self) -> None:
        self.passes += 1
        if self.passes > self.left:
            raise _Passes

    def sleep(self, s: float) -> None:
        self.now += s
        self.slept += s


def test_a_loop_of_one_instant_starts_over_at_most_twice_a_second(tmp_path: Path) -> None:
    """Every message at one log time: a pass takes no time, and --loop started over at once,
    again and again (measured: about 1000 passes a second, each a new session for every
    client). A pass of a loop lasts MIN_LOOP_PERIOD_S at least."""
    from dobhil.live.playback import MIN_LOOP_PERIOD_S, serve_recording
    path = tmp_path / "instant.mcap"
    writer = McapWriter(path)
    for i in range(3):
        writer.on_message_received(can.Message(timestamp=5.0, arbitration_id=0x10 + i, data=[i], is_rx=True))
    writer.stop()
    server = _CountingServer(passes=5)
    with pytest.raises(_Passes):
        serve_recording(path, server, loop=True, wait_for_client=False,  # type: ignore[arg-type]
                        clock=lambda: server.now, sleep=server.sleep)
    assert server.now >= 4 * MIN_LOOP_PERIOD_S  # four passes done, the fifth begun
