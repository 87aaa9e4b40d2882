"""The ``dobhil log serve`` command body (the parser lives in :mod:`dobhil.cli.log_cmd`)."""

from __future__ import annotations

import os
import sys
import time
from typing import Final

from dobhil.live.address import check_bindable, exposure_warning, parse_live_address
from dobhil.live.playback import RecordedChannel, check_speed, load_channels, serve_recording
from dobhil.live.server import LiveServer, import_sdk

_FLUSH_S: Final = 5.0
_GRACE_S: Final = 0.5
#: after the first subscription, for the client to subscribe its other panels' topics
_SETTLE_S: Final = 0.5


def serve_command(path: str | os.PathLike[str], *, live: str, speed: float, loop: bool) -> int:
    """Check every input, then serve ``path`` until played (or Ctrl-C with ``loop``)."""
    address = parse_live_address(live)
    host, port = address
    check_speed(speed)
    import_sdk()
    notes: list[str] = []
    channels = load_channels(path, on_note=notes.append)
    check_bindable(address)  # an unknown host or a busy port: its one line, no exposure warning before it
    warning = exposure_warning(address)
    if warning is not None:
        print(f"warning: {warning}", file=sys.stderr, flush=True)
    for note in notes:   # once every input is checked: bad input stays its one line
        print(f"dobhil log: note: {note}", file=sys.stderr, flush=True)
    # the channels advertised before it listens: a client that connects at once is not refused one
    with LiveServer(host=host, port=port, channels=[c.live() for c in channels]) as server:

        def ready(served: tuple[RecordedChannel, ...]) -> None:
            topics = ", ".join(c.topic for c in served)
            print(f"serving {os.fspath(path)} on {server.url} ({topics})", flush=True)
            print("in Foxglove: Open connection > Foxglove WebSocket > " + server.url, flush=True)
            print("waiting for a client to subscribe (Ctrl-C to stop)", flush=True)

        report = serve_recording(path, server, speed=speed, loop=loop, settle_s=_SETTLE_S,
                                  on_ready=ready)
        server.flush(timeout=_FLUSH_S)
        time.sleep(_GRACE_S)  # the SDK writes its per-client outboxes; stopping would cut them
    print(
        f"served {report.published} messages in {report.passes} pass(es), {report.wall_s:.3f} s; "
        f"dropped {server.dropped}",
        flush=True,
    )
    return 0
