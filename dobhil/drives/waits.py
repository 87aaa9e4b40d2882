"""What every wait on a drive shares (the enable, the preflight's listening, the safe
stop's confirmation): it reads the bus in slices of at most :data:`WAIT_SLICE` s and
asks its ``cancel`` between them, so a stop request (SIGINT, SIGTERM) ends it within one
slice, however long the wait itself (a profile's ``enable_timeout``, a preflight window).
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["WAIT_SLICE", "Cancel"]

#: longest single blocking read of a wait that can be cancelled
WAIT_SLICE = 0.02
#: ``cancel`` of the waits: the reason to stop waiting (e.g. "received SIGINT"), "" to go on
Cancel = Callable[[], str]
