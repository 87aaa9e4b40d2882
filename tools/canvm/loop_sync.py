#!/usr/bin/env python3
"""``dobhil run`` with every periodic frame sent by the loop itself, on any bus (SocketCAN too).

dobhil lets a periodic frame (CiA 402's SYNC) be sent outside its own Python threads only
where the bus does that natively (:func:`dobhil.drives.periodic.native_periodic`: SocketCAN's
broadcast manager); on any other bus -- and behind a wrapper that does not forward the
periodic send, as ``tests/drives/test_periodic.py`` writes one -- the CiA 402 drive sends
the SYNC right after each torque frame and the run needs ``loop.timing: host``
(:mod:`dobhil.drives.cia402.drive`). This runs the same session as ``dobhil run``
(:class:`dobhil.runtime.session.RunSession`, preflight included) behind such a wrapper, so
that the loop-sent SYNC can be measured on the very kernel the native one runs on
(``tools/canvm/figures.py``, figure ``bcm_sync_jitter``)::

    python tools/canvm/loop_sync.py configs/cia402-demo.yaml --bus socketcan:vcan0 --duration 5

It sets ``loop.timing: host`` itself and prints the run's summary (``dobhil run
--summary-json``'s object) with the drive's ``sample_clock``, as one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import can


class LoopSendsPeriodic(can.BusABC):
    """``inner``'s frames both ways, its periodic send not forwarded: ``send_periodic`` here
    would be python-can's thread of this process, so a drive sends such frames itself."""

    def __init__(self, inner: can.BusABC, **kwargs: Any) -> None:
        self._inner = inner
        self.channel_info = f"loop-sent periodic frames on {inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None) or "", **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        # straight through, as dobhil's own recording wrapper does: BusABC.recv's filter
        # and timing bookkeeping would cost this loop what the native one does not pay
        return self._inner.recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), False


def run(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """The run's summary (``dobhil run --summary-json``) and the drive's ``sample_clock``."""
    from dobhil.cli.common import add_config_args, config_from_args
    from dobhil.config import resolve_config
    from dobhil.runtime.session import RunSession, summary
    from dobhil.runtime.signals import stop_on_signals
    from dobhil.runtime.loop import StopRequest
    parser = argparse.ArgumentParser(prog="loop_sync.py", description=__doc__.split("\n\n")[0])
    add_config_args(parser)
    parser.add_argument("--bus", required=True, metavar="INTERFACE:CHANNEL")
    parser.add_argument("--duration", type=float, metavar="S")
    args = parser.parse_args(argv)
    args.overrides = [*args.overrides, "loop.timing=host"]
    config = config_from_args(args)
    with stop_on_signals(StopRequest()) as request, \
            RunSession(config, bus=args.bus, duration=args.duration, stop_request=request,
                       config_dir=resolve_config(args.config).parent, bus_wrapper=LoopSendsPeriodic) as session:
        result = session.run()
        return {**summary(session, result), "sample_clock": session.drive.sample_clock}


def main(argv: Sequence[str] | None = None) -> int:
    info = run(argv)
    print(json.dumps(info), flush=True)
    return 0 if info["stop_reason"] == "done" else 1


if __name__ == "__main__":
    sys.exit(main())
