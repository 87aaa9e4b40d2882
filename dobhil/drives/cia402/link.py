"""canopen on the drive's own bus, with no thread of canopen's: start-up's SDO and NMT.

canopen reads a bus through a ``can.Notifier`` thread that feeds every frame to
``Network.notify``; its SDO client then blocks on a queue (wall-clock timeout) until that
thread has put the answer there. dobhil cannot take that design:

- the drive's bus is borrowed and read by the drive itself (``poll``); a second reader
  would steal the drive's frames;
- in lockstep, simulated time only moves while the host reads the bus: a client that
  sleeps on a wall-clock queue while another thread reads would never see time pass
  (or, worse, see it pass at a thread switch's whim: not deterministic);
- waits on a drive are sliced by WAIT_SLICE and cancellable (a SIGINT ends them).

So :class:`SdoBusAdapter` stands in as the ``Network``'s ``bus`` (canopen only calls its
``send``): it puts the frame on the drive's bus and, when the frame is an SDO request
that the node answers, reads the bus itself -- on the drive's clock, in WAIT_SLICE
slices, asking ``cancel`` between them -- until the node's SDO response (0x580 + node)
arrived, feeding every frame read to ``Network.notify`` (canopen's documented entry for
custom interfaces) and handing the ones that are not SDO to the drive's decoder. When
``send`` returns, canopen's blocking SDO client finds its answer already queued; it is
told not to wait on its own (``RESPONSE_TIMEOUT = 0``), so a missing answer comes back
as canopen's own timeout (``SdoCommunicationError``, after which it sends the abort as
usual) once the adapter has waited ``sdo_timeout`` on the drive's clock. Nothing runs in
another thread.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, cast

import can
import canopen

from dobhil.drives.cia402.codec import Cob
from dobhil.drives.waits import Cancel, sliced_frames
from dobhil.errors import BusError, exception_line

if TYPE_CHECKING:
    from canopen.objectdictionary import ObjectDictionary

__all__ = ["CanopenLink", "SdoBusAdapter", "quiet_canopen"]

Clock = Callable[[], float]
FrameSink = Callable[[can.Message], None]

#: SDO client command specifier of an abort (byte 0, bits 5-7 = 4): the node never answers it
_CCS_MASK = 0xE0
_CCS_ABORT = 0x80
#: initiate download (1), initiate upload (2), block upload (5) and download (6): they name
#: the object (bytes 1-3); segments do not
_CCS_INITIATE = frozenset({0x20, 0x40, 0xA0, 0xC0})


def _never_cancelled() -> str:
    return ""


class SdoBusAdapter:
    """What canopen's ``Network`` sees as its bus: ``send`` sends, then (for an SDO request)
    reads the drive's bus until the node's answer arrived or ``timeout`` s passed on
    ``clock``. ``cancel`` (settable per operation) ends a wait with WaitCancelled within
    WAIT_SLICE s; ``on_frame`` gets every frame read that is not the SDO response."""

    def __init__(self, bus: can.BusABC, *, node_id: int, clock: Clock, timeout: float,
                 on_frame: FrameSink) -> None:
        self._bus = bus
        self._request_id = Cob.SDO_RX + node_id
        self._response_id = Cob.SDO_TX + node_id
        self._clock = clock
        self._on_frame = on_frame
        self.timeout = timeout
        self.cancel: Cancel = _never_cancelled
        self.network: canopen.Network | None = None
        #: (index, sub-index) of the last SDO transfer started: what a failure names
        self.last_object = (0, 0)
        self.channel_info = f"canopen link over {bus.channel_info}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        request = msg.arbitration_id == self._request_id and len(msg.data) > 0
        ccs = msg.data[0] & _CCS_MASK if request else _CCS_ABORT
        if ccs in _CCS_INITIATE and len(msg.data) >= 4:
            self.last_object = (msg.data[1] | msg.data[2] << 8, msg.data[3])
        try:
            self._bus.send(msg, timeout)
        except can.CanError:
            raise  # python-can's own: canopen's SDO client knows it (and gives up at once)
        except Exception as exc:  # a transport's own error (python-can-remote's, say)
            raise BusError(exception_line(exc)) from exc
        if request and ccs != _CCS_ABORT:
            self._await_response()

    def _await_response(self) -> None:
        """Read until the SDO response is in canopen's queue (or give up: canopen then
        reports its own timeout)."""
        frames = sliced_frames(self._read, self._clock, self._clock() + self.timeout,
                               cancel=self.cancel, what="waiting for an SDO answer")
        any(self._dispatch(msg) for msg in frames)

    def _read(self, timeout: float) -> can.Message | None:
        try:
            return self._bus.recv(timeout)
        except Exception as exc:  # any interface's read failure is the bus's
            raise BusError(f"bus read failed: {exception_line(exc)}") from exc

    def _dispatch(self, msg: can.Message) -> bool:
        """Feed one frame to canopen and (not SDO) to the drive; True if it was the answer."""
        if msg.is_error_frame or msg.is_remote_frame:
            return False
        if self.network is not None:
            try:
                self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)
            except Exception:  # as canopen's own MessageListener: a callback's failure on a
                pass           # malformed frame (an EMCY of 2 bytes) must not end the read
        if msg.arbitration_id == self._response_id:
            return True
        self._on_frame(msg)
        return False


class CanopenLink:
    """A canopen ``Network`` with one ``RemoteNode`` on the drive's bus, through
    :class:`SdoBusAdapter` (no notifier, no thread). ``node`` is canopen's node: its
    ``sdo``, ``nmt``, ``rpdo``/``tpdo`` and object dictionary are used as canopen documents
    them."""

    def __init__(self, bus: can.BusABC, od: ObjectDictionary, *, node_id: int, clock: Clock,
                 sdo_timeout: float, on_frame: FrameSink) -> None:
        self.adapter = SdoBusAdapter(bus, node_id=node_id, clock=clock, timeout=sdo_timeout,
                                     on_frame=on_frame)
        # canopen types Network.bus as a python-can bus but only ever calls its send()
        # (send_periodic only through Network.send_periodic, which dobhil does not use)
        self.network = canopen.Network(cast(can.BusABC, self.adapter))
        self.adapter.network = self.network
        self.node = self.network.add_node(node_id, od)
        # the adapter has waited on the drive's clock before canopen looks into its
        # queue: canopen must not wait again on the wall clock (see the module's docstring)
        self.node.sdo.RESPONSE_TIMEOUT = 0.0

    @contextmanager
    def session(self, cancel: Cancel | None) -> Iterator[_CanopenLog]:
        """Within: SDO waits ask ``cancel``, and canopen's log records (its SDO client logs
        an error when it aborts a transfer) are collected instead of reaching Python's
        last-resort handler, which would print them above dobhil's one line."""
        self.adapter.cancel = cancel if cancel is not None else _never_cancelled
        try:
            with quiet_canopen() as log:
                yield log
        finally:
            self.adapter.cancel = _never_cancelled


@contextmanager
def quiet_canopen() -> Iterator[_CanopenLog]:
    """canopen's log records collected, not printed by Python's last-resort handler (its
    PDO map logs a warning for a mapping beyond 64 bits that dobhil reports itself)."""
    log = _CanopenLog()
    logger = logging.getLogger("canopen")
    logger.addHandler(log)
    try:
        yield log
    finally:
        logger.removeHandler(log)


class _CanopenLog(logging.Handler):
    """canopen's warnings during a session, one line each (for a message that needs them)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(" ".join(record.getMessage().split()))
