"""A minimal Foxglove WebSocket client for tests (``from live_client import LiveClient``).

Speaks the Foxglove WebSocket protocol as a Foxglove app does: offers the
``foxglove.sdk.v1`` subprotocol (what foxglove-sdk 0.30 accepts) and the older
``foxglove.websocket.v1`` (the same messages under their first name), reads the
``advertise`` messages, subscribes by topic and decodes ``messageData`` frames:
opcode 1, subscription id (u32), log time (u64, ns), payload, little-endian.
Written here because the protocol client libraries are JavaScript/C++; the
``websockets`` package does the WebSocket part.
"""

from __future__ import annotations

import itertools
import json
import struct
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, NamedTuple

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
OP_MESSAGE_DATA = 0x01
#: a closing client reads until the server has been quiet this long (seconds)
_QUIET_S = 0.05
_HEADER = struct.Struct("<BIQ")


class Received(NamedTuple):
    """One messageData frame, decoded."""

    topic: str
    log_time_ns: int
    payload: bytes


def decode_message_data(frame: bytes) -> tuple[int, int, bytes]:
    """(subscription id, log time ns, payload) of a binary messageData frame."""
    opcode, subscription, log_time = _HEADER.unpack_from(frame)
    if opcode != OP_MESSAGE_DATA:
        raise ValueError(f"binary opcode {opcode}, expected {OP_MESSAGE_DATA} (messageData)")
    return subscription, log_time, bytes(frame[_HEADER.size:])


class LiveClient:
    """A connected client: advertised channels by topic, subscriptions, received messages."""

    def __init__(self, url: str, *, open_timeout: float = 10.0, max_queue: int = 64) -> None:
        connection = connect(
            url, subprotocols=list(SUBPROTOCOLS), open_timeout=open_timeout, max_queue=max_queue,
            compression=None, proxy=None, ping_interval=None,  # a stalled test client must not time out
        )
        self.ws: ClientConnection = connection.__enter__()  # the context-manager form websockets asks for
        self.subprotocol = self.ws.subprotocol
        self.channels: dict[str, dict[str, Any]] = {}  # advertised now
        self.advertised: dict[str, dict[str, Any]] = {}  # ever advertised (unadvertise keeps them here)
        self.server_info: dict[str, Any] = {}
        self.texts: list[dict[str, Any]] = []
        self._topics_by_subscription: dict[int, str] = {}
        self._ids = itertools.count(1)

    def __enter__(self) -> LiveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Unsubscribe, read what is still on its way, then close. websockets stops reading
        the socket while ``max_queue`` messages wait unread (its backpressure), and the
        server's answer to the close frame queues behind them: a client that stopped reading
        a busy stream waited out ``close_timeout`` (10 s) in ``close()`` (measured: 10.2-10.3 s
        in three of four lockstep runs of tests/recording/test_live_run.py)."""
        try:
            if self._topics_by_subscription:
                self.ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": list(self._topics_by_subscription)}))
            while True:
                self.ws.recv(timeout=_QUIET_S)
        except (TimeoutError, ConnectionClosed):
            pass
        self.ws.close()

    def _handle_text(self, text: str) -> None:
        message = json.loads(text)
        op = message.get("op")
        if op == "serverInfo":
            self.server_info = message
        elif op == "advertise":
            self.channels.update({c["topic"]: c for c in message["channels"]})
            self.advertised.update({c["topic"]: c for c in message["channels"]})
        elif op == "unadvertise":
            gone = set(message["channelIds"])
            self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}
        else:
            self.texts.append(message)

    def _receive(self, timeout: float) -> Received | None:
        """Handle one frame; a decoded message for binary messageData, else None."""
        frame = self.ws.recv(timeout=timeout)
        if isinstance(frame, str):
            self._handle_text(frame)
            return None
        if frame[0] != OP_MESSAGE_DATA:
            return None
        subscription, log_time, payload = decode_message_data(frame)
        return Received(self._topics_by_subscription[subscription], log_time, payload)

    def wait_for_channels(self, topics: Iterable[str], timeout: float = 10.0) -> dict[str, dict[str, Any]]:
        """Read until every topic is advertised; the advertised channels by topic."""
        wanted = set(topics)
        deadline = time.monotonic() + timeout
        while not wanted <= self.channels.keys():
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"not advertised within {timeout} s: {sorted(wanted - self.channels.keys())}")
            self._receive(left)
        return {t: self.channels[t] for t in wanted}

    def subscribe(self, topics: Sequence[str], timeout: float = 10.0) -> None:
        """Subscribe to advertised topics (waiting for their advertisement)."""
        channels = self.wait_for_channels(topics, timeout)
        subscriptions = []
        for topic in topics:
            sub_id = next(self._ids)
            self._topics_by_subscription[sub_id] = topic
            subscriptions.append({"id": sub_id, "channelId": channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def collect(
        self, done: Callable[[list[Received]], bool], timeout: float = 30.0
    ) -> list[Received]:
        """Received messages until ``done(received)`` is true; TimeoutError after ``timeout``."""
        received: list[Received] = []
        deadline = time.monotonic() + timeout
        while not done(received):
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"condition not met within {timeout} s after {len(received)} messages")
            try:
                message = self._receive(left)
            except TimeoutError:
                continue
            if message is not None:
                received.append(message)
        return received

    def drain(self, quiet: float = 1.0) -> list[Received]:
        """Every message that arrives until none has for ``quiet`` seconds."""
        received: list[Received] = []
        while True:
            try:
                message = self._receive(quiet)
            except TimeoutError:
                return received
            if message is not None:
                received.append(message)


def counts_at_least(minimum: dict[str, int]) -> Callable[[list[Received]], bool]:
    """A ``collect`` condition: at least ``minimum[topic]`` messages of each topic."""

    have: dict[str, int] = {}
    seen = 0

    def done(received: list[Received]) -> bool:
        nonlocal seen
        for r in received[seen:]:
            have[r.topic] = have.get(r.topic, 0) + 1
        seen = len(received)
        return all(have.get(t, 0) >= n for t, n in minimum.items())

    return done
