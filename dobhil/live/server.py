"""A Foxglove WebSocket server for dobhil channels that never blocks its caller.

What foxglove-sdk does (0.25-0.30, measured by hand and checked by
``tests/live/test_server.py``): ``Channel.log`` never waits for a client. Each client
has its own outbox of ``message_backlog_size`` messages (1024 by default); when it
is full the SDK drops that client's *oldest* data messages and logs one throttled
``outbox for client ... full`` line, but counts them on no public API. With one
client that never reads, 100 000 logs of 320-byte messages cost 2-6 us each on
average, yet 28-830 us at the 99.9th percentile and up to 8-180 ms for the slowest
call on a loaded 2-core machine; the cost also grows with the number of clients.

So :class:`LiveServer` puts its own bounded queue and one sender thread in front of
the SDK: :meth:`LiveServer.publish` is a dict lookup, a length check and a deque
append whatever the clients do (same test: 1.7-3 us on average, 18-20 us at the
99.9th percentile, 21-34 ms at worst, a switch of the interpreter lock). When
``max_pending`` messages wait it drops the new one and counts it in
:attr:`LiveServer.dropped`. The per-client drops inside the SDK remain uncounted
(see ``docs/foxglove.md``).
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Iterable, Mapping
from types import TracebackType
from typing import Any, Final, NamedTuple

from dobhil.errors import ConfigError, DobhilError
from dobhil.live.address import DEFAULT_HOST

#: The WebSocket subprotocol foxglove-sdk 0.30 speaks (same messages as foxglove.websocket.v1).
SUBPROTOCOL: Final = "foxglove.sdk.v1"
INSTALL_HINT: Final = "pip install 'dobhil[live]'"
_JOIN_TIMEOUT_S: Final = 5.0


class LiveUnavailableError(DobhilError, ImportError):
    """The live view was asked for but foxglove-sdk is not installed."""


class LiveServerError(DobhilError, OSError):
    """The live view could not listen where it was asked to."""


class LiveChannelError(ConfigError):
    """A live channel was added twice, or a message names no added channel."""


def import_sdk() -> Any:
    """The ``foxglove`` module, or one :class:`LiveUnavailableError` line naming the extra."""
    try:
        import foxglove
    except ImportError as exc:
        raise LiveUnavailableError(f"the live view needs foxglove-sdk, which is not installed: {INSTALL_HINT}") from exc
    return foxglove


class _Subscriptions:
    """A foxglove ``ServerListener``: how many (client, channel) subscriptions are open."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self.count = 0

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._changed:
            self.count += 1
            self._changed.notify_all()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._changed:
            self.count = max(0, self.count - 1)
            self._changed.notify_all()

    def wait(self, timeout: float | None) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: self.count > 0, timeout)


_Pending = tuple[Any, bytes, int]


class LiveChannel(NamedTuple):
    """A channel to advertise (the arguments of :meth:`LiveServer.add_channel`)."""

    topic: str
    schema_name: str
    schema: Mapping[str, Any] | bytes
    message_encoding: str = "json"
    schema_encoding: str = "jsonschema"


class LiveServer:
    """Serves channels to Foxglove clients; :meth:`publish` never blocks.

    Give the channels known up front as ``channels`` (:class:`LiveChannel`, or tuples of its
    fields): they are advertised before the server
    listens, so no client can be refused a subscription to one of them (see ``__init__``);
    a channel added later by :meth:`add_channel` races a client already connected.

    Publish from one thread (e.g. the recorder's writer thread); the counters are
    exact for a single publishing thread.

    ``LiveServer(port=0)`` picks a free port (:attr:`port`); the host is 127.0.0.1
    unless one is given. Use it as a context manager or call :meth:`close`.
    ``max_pending`` bounds the messages waiting for the sender thread (beyond it
    :meth:`publish` drops and counts); ``backlog`` is the SDK's per-client outbox.
    """

    def __init__(
        self,
        *,
        host: str = DEFAULT_HOST,
        port: int,
        name: str = "dobhil",
        max_pending: int = 65536,
        backlog: int = 1024,
        channels: Iterable[LiveChannel | tuple[Any, ...]] = (),
    ) -> None:
        if max_pending < 1 or backlog < 1:
            raise ConfigError(f"max_pending and backlog must be >= 1, got {max_pending} and {backlog}")
        self._sdk = import_sdk()
        self._context = self._sdk.Context()
        self._subscriptions = _Subscriptions()
        self._channels: dict[str, Any] = {}
        self._closing = False
        # Before the server listens: foxglove-sdk (0.30.3, connected_client.rs advertise_channels)
        # sends the advertisement of a channel added while a client is connected before it
        # records the channel as that client's, and refuses a subscription that comes back in
        # between ("Unknown channel ID"): a Foxglove left open on the address, which connects
        # the moment something listens, was refused about one try in four and `log serve`
        # waited for it forever. A client that connects later is told of these channels
        # before its messages are read (server.rs register_client_and_advertise).
        for c in (LiveChannel(*fields) for fields in channels):
            self.add_channel(c.topic, schema_name=c.schema_name, json_schema=c.schema,
                             message_encoding=c.message_encoding, schema_encoding=c.schema_encoding)
        try:
            self._server = self._sdk.start_server(
                name=name,
                host=host,
                port=port,
                context=self._context,
                server_listener=self._subscriptions,
                message_backlog_size=backlog,
                # read-only for whoever connects: no client publishing, parameters, services,
                # assets or connection graph (the SDK refuses each with an error status)
                capabilities=[],
            )
        except RuntimeError as exc:
            raise LiveServerError(f"live view cannot listen on {host}:{port}: {exc}") from exc
        self.host = host
        self.port: int = self._server.port
        self._max_pending = max_pending
        self._pending: deque[_Pending] = deque()
        self._wake = threading.Event()
        self._drop_lock = threading.Lock()
        self._dropped = 0
        self._sent = 0
        self._accepted = 0
        self._failed = 0
        self._closed = False
        self._close_lock = threading.Lock()
        self._sender = threading.Thread(target=self._send_loop, name="dobhil-live-sender", daemon=True)
        self._sender.start()

    @property
    def url(self) -> str:
        """``ws://HOST:PORT`` to open in Foxglove."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    @property
    def dropped(self) -> int:
        """Messages :meth:`publish` dropped (queue full, or published after :meth:`close`)."""
        return self._dropped

    @property
    def sent(self) -> int:
        """Messages handed to the SDK for every subscribed client."""
        return self._sent

    @property
    def topics(self) -> tuple[str, ...]:
        """Topics of the advertised channels, in the order added."""
        return tuple(self._channels)

    @property
    def subscriptions(self) -> int:
        """Open (client, channel) subscriptions."""
        return self._subscriptions.count

    def wait_for_subscriber(self, timeout: float | None = None) -> bool:
        """Block until some client subscribes to some channel; False on timeout."""
        return self._subscriptions.wait(timeout)

    def add_channel(self, topic: str, *, schema_name: str, json_schema: Mapping[str, Any] | bytes,
                    message_encoding: str = "json", schema_encoding: str = "jsonschema") -> None:
        """Advertise ``topic`` (message encoding json, schema encoding jsonschema, unless given:
        a recording's protobuf channels are served as they are stored).

        ``json_schema`` is the schema as a dict, or as bytes passed on unchanged
        (e.g. exactly as stored in an MCAP schema record).
        """
        if self._closing:
            raise LiveChannelError(f"live channel {topic!r}: the server is closed")
        if topic in self._channels:
            raise LiveChannelError(f"live channel {topic!r} was already added")
        data = json_schema if isinstance(json_schema, bytes) else json.dumps(json_schema).encode()
        schema = self._sdk.Schema(name=schema_name, encoding=schema_encoding, data=data)
        self._channels[topic] = self._sdk.Channel(topic, schema=schema, message_encoding=message_encoding,
                                                  context=self._context)

    def publish(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        """Queue one JSON message for every subscribed client; never blocks.

        Drops the message (and counts it in :attr:`dropped`) when ``max_pending``
        messages already wait or the server is closed. An unknown topic is a caller
        bug: :class:`LiveChannelError`.
        """
        channel = self._channels.get(topic)
        if channel is None:
            raise LiveChannelError(f"no live channel {topic!r}; added: {', '.join(self._channels) or 'none'}")
        if self._closing or len(self._pending) >= self._max_pending:
            with self._drop_lock:
                self._dropped += 1
            return
        self._pending.append((channel, payload, log_time_ns))
        self._accepted += 1
        # Set after the append: if the sender clears the event after this check, its
        # drain that follows the clear sees the message.
        if not self._wake.is_set():
            self._wake.set()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every queued message went to the SDK; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self._sent + self._failed < self._accepted:
            if deadline is not None and time.monotonic() >= deadline:
                return False
            if self._closed:
                return False
            time.sleep(0.001)
        return True

    def new_session(self) -> None:
        """Tell clients to forget what they have (e.g. when a playback starts over)."""
        self._server.clear_session()

    def _send_loop(self) -> None:
        while True:
            self._wake.wait()
            self._wake.clear()
            self._drain()
            if self._closing and not self._pending:
                return

    def _drain(self) -> None:
        pending = self._pending
        while True:
            try:
                channel, payload, log_time = pending.popleft()
            except IndexError:
                return
            try:
                channel.log(payload, log_time=log_time)
            except Exception:  # e.g. a negative log time: counted, and the sender keeps going
                with self._drop_lock:
                    self._dropped += 1
                self._failed += 1
                continue
            self._sent += 1

    def close(self) -> None:
        """Send what is queued, unadvertise the channels, stop the server; idempotent."""
        with self._close_lock:
            if self._closed:
                return
            self._closing = True
            self._wake.set()
            self._sender.join(_JOIN_TIMEOUT_S)
            with self._drop_lock:  # published while closing, after the last drain
                self._dropped += len(self._pending)
                self._pending.clear()
            for channel in self._channels.values():
                channel.close()
            self._server.stop()
            self._closed = True

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"LiveServer({self.url}, {state}, sent={self._sent}, dropped={self._dropped})"


__all__ = [
    "INSTALL_HINT",
    "SUBPROTOCOL",
    "LiveChannel",
    "LiveChannelError",
    "LiveServer",
    "LiveServerError",
    "LiveUnavailableError",
    "import_sdk",
]
