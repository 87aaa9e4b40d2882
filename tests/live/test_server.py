"""LiveServer against a real WebSocket client: payloads intact, never blocks, drops counted."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import jsonschema
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from live_client import LiveClient, counts_at_least

from dobhil.live import LiveServer, LiveUnavailableError
from dobhil.live.server import INSTALL_HINT, LiveChannelError, LiveServerError
from dobhil.recording.schemas import spec_for

TOPICS = ("/controller", "/can/rx")


def _payloads(topic: str, n: int) -> list[bytes]:
    if topic == "/controller":
        values = [{"tau_ref": 0.1 * i, "tau_int_hat": -0.5, "tau_dis_hat": 1e-9, "tau_per": 0.0,
                   "u_unsat": 2.5, "u_sat": 2.0, "cycle": i} for i in range(n)]
    else:
        values = [{"timestamp": i * 1e-3, "arbitration_id": 0x009, "is_extended_id": False,
                   "is_remote_frame": False, "is_error_frame": False, "is_fd": False, "bitrate_switch": False,
                   "error_state_indicator": False, "dlc": 8, "data": [i % 256, 0, 0, 0, 1, 2, 3, 4],
                   "data_hex": f"{i % 256:02x}00000001020304", "direction": "rx", "channel": "demo"}
                  for i in range(n)]
    return [json.dumps(v, separators=(",", ":")).encode() for v in values]


def _server(**kwargs: int) -> LiveServer:
    server = LiveServer(port=0, **kwargs)
    for topic in TOPICS:
        spec = spec_for(topic)
        server.add_channel(topic, schema_name=spec.schema_name, json_schema=spec.json_schema())
    return server


def test_client_receives_payloads_intact_and_valid() -> None:
    n = 300
    sent = {t: _payloads(t, n) for t in TOPICS}
    with _server() as server, LiveClient(server.url) as client:
        assert server.url == f"ws://127.0.0.1:{server.port}" and server.port > 0
        assert client.subprotocol in ("foxglove.sdk.v1", "foxglove.websocket.v1")
        client.subscribe(TOPICS)
        assert server.wait_for_subscriber(timeout=10)
        deadline = time.monotonic() + 10
        while server.subscriptions < len(TOPICS) and time.monotonic() < deadline:
            time.sleep(0.01)
        for i in range(n):
            for topic in TOPICS:
                server.publish(topic, sent[topic][i], 1_000_000_000 + i * 1_000_000)
        received = client.collect(counts_at_least({t: n for t in TOPICS}), timeout=30)
        advertised = client.advertised
    assert server.dropped == 0 and server.sent == 2 * n
    for topic in TOPICS:
        got = [r for r in received if r.topic == topic]
        assert [r.payload for r in got] == sent[topic]
        assert [r.log_time_ns for r in got] == [1_000_000_000 + i * 1_000_000 for i in range(n)]
        channel = advertised[topic]
        assert (channel["encoding"], channel["schemaEncoding"]) == ("json", "jsonschema")
        assert channel["schemaName"] == spec_for(topic).schema_name
        schema = json.loads(channel["schema"])
        assert schema == spec_for(topic).json_schema()
        for r in got:
            jsonschema.validate(json.loads(r.payload), schema)


def test_publish_without_client_returns_and_counts_nothing_lost() -> None:
    """20,000 messages, fewer than the default queue holds (65,536): none may be dropped,
    however slow the sender thread; every one reaches the SDK (flush waits for it, with
    no time bound), and close loses none."""
    payload = _payloads("/controller", 1)[0]
    n = 20_000
    with _server() as server:
        for i in range(n):
            server.publish("/controller", payload, i)
        assert server.flush()
        assert (server.sent, server.dropped) == (n, 0)
    assert (server.sent, server.dropped) == (n, 0)


def test_full_queue_drops_new_messages_and_counts_them() -> None:
    payload = _payloads("/controller", 1)[0]
    n = 50_000
    with _server(max_pending=1) as server:
        for i in range(n):  # the sender thread cannot keep one slot free for a tight loop
            server.publish("/controller", payload, i)
    assert server.sent + server.dropped == n
    assert server.dropped > 0


def test_client_that_never_reads_does_not_block_publish() -> None:
    """The SDK drops a stalled client's oldest messages; publish keeps returning."""
    n = 100_000
    payload = json.dumps({"tau_ref": 1.0, "pad": "x" * 300}).encode()
    with _server(backlog=64) as server, LiveClient(server.url, max_queue=1) as stalled:
        stalled.subscribe(["/controller"])
        assert server.wait_for_subscriber(timeout=10)
        done = threading.Event()

        def flood() -> None:
            for i in range(n):
                server.publish("/controller", payload, i)
            done.set()

        thread = threading.Thread(target=flood, daemon=True)
        thread.start()
        assert done.wait(timeout=120), "publish blocked behind a client that does not read"
        assert server.flush(timeout=60)
        assert server.sent + server.dropped == n
        received = stalled.drain(quiet=1.0)
    assert len(received) < server.sent  # far more than a socket buffer and the outbox hold
    times = [r.log_time_ns for r in received]
    assert times == sorted(set(times))  # in order, none twice
    assert times[-1] > n // 2  # the outbox drops old messages, not the flood's tail
    assert all(r.payload == payload for r in received)


def test_close_is_idempotent_and_publish_after_close_is_a_counted_drop() -> None:
    server = _server()
    server.close()
    server.close()
    server.publish("/controller", b"{}", 0)
    assert server.dropped == 1
    with pytest.raises(LiveChannelError):
        server.add_channel("/x", schema_name="x", json_schema={"type": "object"})


def test_unknown_topic_and_duplicate_channel_are_errors() -> None:
    with _server() as server:
        with pytest.raises(LiveChannelError, match="no live channel '/nope'"):
            server.publish("/nope", b"{}", 0)
        with pytest.raises(LiveChannelError, match="already added"):
            server.add_channel("/controller", schema_name="x", json_schema={"type": "object"})


def test_busy_port_is_one_line_error() -> None:
    with _server() as first, pytest.raises(LiveServerError, match="cannot listen on 127.0.0.1") as info:
        LiveServer(port=first.port)
    assert "\n" not in str(info.value)


def test_without_sdk_dobhil_imports_and_live_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "foxglove", None)
    with pytest.raises(LiveUnavailableError, match="pip install 'dobhil\\[live\\]'"):
        LiveServer(port=0)
    assert INSTALL_HINT == "pip install 'dobhil[live]'"


def test_without_sdk_cli_serve_exits_2_with_one_line(tmp_path) -> None:  # type: ignore[no-untyped-def]
    script = (
        "import sys; sys.modules['foxglove'] = None\n"
        "import dobhil, dobhil.live, dobhil.cli.main as m\n"
        "sys.exit(m.main(['log', 'serve', sys.argv[1], '--live', '0']))\n"
    )
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path / "any.mcap")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().count("\n") == 0
    assert "pip install 'dobhil[live]'" in proc.stderr and "Traceback" not in proc.stderr


@settings(max_examples=25, deadline=None)
@given(
    times=st.lists(st.integers(-5, 2**64 + 5), max_size=300),
    max_pending=st.integers(1, 50),
)
def test_every_publish_is_sent_or_counted(times: list[int], max_pending: int) -> None:
    with _server(max_pending=max_pending) as server:
        for t in times:
            server.publish("/can/rx", b'{"dlc": 8}', t)
        assert server.flush(timeout=30)
        bad = sum(1 for t in times if not 0 <= t < 2**64)  # log times the SDK refuses
        assert server.sent + server.dropped == len(times)
        assert server.dropped >= bad


def test_a_client_cannot_publish_call_services_or_change_anything() -> None:
    """The live view is read-only whoever connects (docs/foxglove.md): the server offers no
    capability, refuses every write a Foxglove client can send, and serves the same
    channels and data afterwards, to this client and to a new one."""
    import struct
    writes = [
        json.dumps({"op": "advertise", "channels": [{"id": 7, "topic": "/controller", "encoding": "json",
                                                     "schemaName": "x"}]}),
        struct.pack("<BI", 1, 7) + b'{"tau_ref": 99}',                   # clientMessageData on it
        json.dumps({"op": "setParameters", "parameters": [{"name": "design.force_gain", "value": 9}], "id": "s"}),
        json.dumps({"op": "getParameters", "parameterNames": [], "id": "g"}),
        json.dumps({"op": "subscribeParameterUpdates", "parameterNames": ["design.force_gain"]}),
        struct.pack("<BIII", 2, 1, 1, 4) + b"json{}",                    # serviceCallRequest
        json.dumps({"op": "fetchAsset", "uri": "file:///etc/passwd", "requestId": 1}),
        json.dumps({"op": "subscribeConnectionGraph"}),
    ]
    payloads = _payloads("/controller", 5)
    with _server() as server, LiveClient(server.url) as client:
        client.wait_for_channels(TOPICS)
        assert client.server_info["capabilities"] == []
        before = dict(client.channels)
        for frame in writes:
            client.ws.send(frame)
        client.subscribe(["/controller"])
        assert server.wait_for_subscriber(timeout=10)
        for i, payload in enumerate(payloads):
            server.publish("/controller", payload, 1_000 + i)
        received = client.collect(counts_at_least({"/controller": len(payloads)}), timeout=30)
        client.drain(0.5)
        refusals = [t for t in client.texts if t.get("op") in ("status", "serviceCallFailure")]
        with LiveClient(server.url) as other:
            other.wait_for_channels(TOPICS)
            other_channels = dict(other.channels)
        assert client.channels == before and other_channels.keys() == before.keys()
    assert [r.payload for r in received] == payloads    # nothing of the client's got in
    assert all(t.get("level", 2) == 2 for t in refusals)  # each refusal an error
    words = " ".join(t["message"] for t in refusals)
    for capability in ("clientPublish", "parameters", "parametersSubscribe", "services", "assets"):
        assert f"support {capability}" in words, words
    answers = ("parameterValues", "serviceCallResponse", "fetchAssetResponse")
    assert not [t for t in client.texts if t.get("op") in answers]
