#!/usr/bin/env python3
"""Bytes per control cycle of one recorded run in three MCAP layouts: what the message index
costs, measured on a real log rather than estimated.

dobhil writes each cycle as several messages (``/loop``, ``/controller``, ``/drive/command``,
``/drive/feedback``, ``/emulator/truth``) and each CAN frame as its own (``/can/rx``,
``/can/tx``), so Foxglove and python-can tools see a topic per signal and per frame. MCAP
indexes every message: 16 bytes (log time, offset) per message in the chunk's message index,
outside the compressed chunk, which Foxglove's indexed reader needs
(``typescript/core/src/ChunkCursor.ts`` in github.com/foxglove/mcap). This tool rewrites the
log's own messages, unchanged, with the ``mcap`` package's writer and dobhil's chunking
(zstd, the same chunk size) in:

- ``per_topic``: as recorded (one message per topic per cycle, one per frame);
- ``signals_merged``: the cycle's signal messages as one message (their protobuf payloads
  concatenated, each as a length-delimited field: what one nested message would hold),
  the frames as recorded;
- ``all_merged``: the frames of the cycle folded into that one message too.

A message belongs to the cycle whose period its log time falls in (the run's
``loop.period`` from the log's metadata). ``all_merged`` is near what ``dobhil run
--log-layout cycle`` writes (``dobhil/recording/cycles.py``, which also keeps each frame's
log time and leaves the frames before the first cycle on their topics); ``signals_merged``
is no layout dobhil writes.

    python tools/log_layouts.py run.mcap            # a line per layout
    python tools/log_layouts.py run.mcap --json
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mcap.reader import make_reader  # noqa: E402
from mcap.writer import Writer  # noqa: E402

from dobhil.recording.reader import LogFile  # noqa: E402
from dobhil.recording.writer import CHUNK_SIZE, COMPRESSION  # noqa: E402

#: the topics whose messages are CAN frames (kept apart in ``signals_merged``)
FRAME_TOPICS = ("/can/rx", "/can/tx")
LAYOUTS = ("per_topic", "signals_merged", "all_merged")

Message = tuple[str, int, bytes]   # topic, log time [ns], payload


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _field(number: int, payload: bytes) -> bytes:
    """One length-delimited protobuf field: how a nested message carries a sub-message."""
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def _written_bytes(messages: Iterable[Message]) -> int:
    """File size of ``messages`` written as dobhil writes a log (zstd chunks, CRCs, index)."""
    buf = io.BytesIO()
    writer = Writer(buf, chunk_size=CHUNK_SIZE, compression=COMPRESSION, enable_data_crcs=True)
    writer.start("", "tools/log_layouts.py")
    schema = writer.register_schema("layout", "protobuf", b"")
    channels: dict[str, int] = {}
    for topic, time_ns, data in messages:
        if topic not in channels:
            channels[topic] = writer.register_channel(topic, "protobuf", schema)
        writer.add_message(channels[topic], log_time=time_ns, data=data, publish_time=time_ns)
    writer.finish()
    return len(buf.getvalue())


def _merged(messages: Sequence[Message], period_ns: int, merge: Sequence[str] | None) -> list[Message]:
    """The messages with those of each cycle on the ``merge`` topics (None: all) as one
    ``/cycle`` message at the cycle's first log time; the others as they were."""
    numbers = {topic: i + 1 for i, topic in enumerate(sorted({t for t, _, _ in messages}))}
    out: list[Message] = []
    cycle: list[Message] = []
    current = None

    def flush() -> None:
        if cycle:
            out.append(("/cycle", cycle[0][1], b"".join(_field(numbers[t], d) for t, _, d in cycle)))
            cycle.clear()
    for topic, time_ns, data in messages:
        k = time_ns // period_ns
        if k != current:
            flush()
            current = k
        if merge is None or topic in merge:
            cycle.append((topic, time_ns, data))
        else:
            out.append((topic, time_ns, data))
    flush()
    return out


def layouts(path: Path) -> dict[str, float]:
    """Bytes per cycle of the log at ``path`` in each of :data:`LAYOUTS`, and its cycles."""
    log = LogFile(path)
    period = float(log.info().metadata["run"]["period"])
    with open(path, "rb") as f:
        messages = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f).iter_messages()]
    cycles = sum(1 for topic, _, _ in messages if topic == "/loop")
    signals = sorted({t for t, _, _ in messages} - set(FRAME_TOPICS))
    period_ns = round(period * 1e9)
    sizes = {"per_topic": _written_bytes(messages),
             "signals_merged": _written_bytes(_merged(messages, period_ns, signals)),
             "all_merged": _written_bytes(_merged(messages, period_ns, None))}
    return {**{k: v / cycles for k, v in sizes.items()}, "cycles": cycles,
            "recorded": path.stat().st_size / cycles}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path, help="a dobhil log (dobhil run ... --log X.mcap)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    figures = layouts(args.log)
    if args.json:
        print(json.dumps(figures, indent=2))
        return 0
    print(f"{args.log}: {figures['cycles']:.0f} cycles, {figures['recorded']:.1f} bytes per cycle as recorded")
    for name in LAYOUTS:
        print(f"  {name:15s} {figures[name]:7.1f} bytes per cycle")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
