"""Live view: serve a run or a recording to Foxglove over WebSocket.

``foxglove-sdk`` is an optional extra (``pip install 'dobhil[live]'``); this
package imports without it and only :class:`LiveServer` asks for it, failing with
one :class:`LiveUnavailableError` line when it is missing.

- :mod:`dobhil.live.address`   ``[HOST:]PORT`` parsing (127.0.0.1 unless a host is given)
- :mod:`dobhil.live.server`    :class:`LiveServer`: channels, non-blocking publish, counted drops
- :mod:`dobhil.live.playback`  ``dobhil log serve``: a recording played at its recorded pace
"""

from __future__ import annotations

from dobhil.live.address import DEFAULT_HOST, LiveAddress, LiveAddressError, parse_live_address
from dobhil.live.server import LiveServer, LiveUnavailableError

__all__ = [
    "DEFAULT_HOST",
    "LiveAddress",
    "LiveAddressError",
    "LiveServer",
    "LiveUnavailableError",
    "parse_live_address",
]
