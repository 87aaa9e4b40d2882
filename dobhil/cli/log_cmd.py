"""``dobhil log``: inspect, recover, export and import recordings.

- ``dobhil log info FILE [--json]``
- ``dobhil log recover FILE [-o OUT]``         (default OUT: ``FILE.recovered.mcap``)
- ``dobhil log export FILE --topic T --format csv [-o OUT]``
- ``dobhil log export FILE --can --format candump|asc|blf [-o OUT]``
- ``dobhil log import CANLOG -o FILE.mcap``
- ``dobhil log convert FILE --layout topics|cycle [-o OUT]``  (default OUT: ``FILE.LAYOUT.mcap``)
- ``dobhil log serve FILE [--live [HOST:]PORT] [--speed X] [--loop]``  (Foxglove live view)

Bad input ends in one :class:`~dobhil.errors.LogFileError` line (exit 2); an output that
is one of the inputs is refused, and outputs appear only when complete. ``info``, ``export``
and ``serve`` read what was recorded without applying its config, so a newer dobhil's log
(a recorded config key this version does not know) is read, with one note line
(:func:`dobhil.recording.reader.unknown_keys_note`). A CAN log cut short
is imported up to its last complete record, with one warning line saying what was dropped (a gzip-compressed
one, ``run.log.gz``, the same: :mod:`dobhil.canio.canlog`). Progress goes to
stderr (:mod:`dobhil.cli.progress`: a bar on a terminal, else lines).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from typing import Any

from dobhil.errors import LogFileError
from dobhil.cli.common import output_path
from dobhil.recording.layouts import LAYOUTS

Progress = Callable[[int], None]


@contextmanager
def _progress(desc: str, total: int | None) -> Iterator[Progress]:
    """An update function (messages done) for :mod:`dobhil.cli.progress` on stderr."""
    from dobhil.cli.progress import progress

    with progress(desc, total=total, unit="message") as shown:
        yield shown.update


def _total(path: str, exported: Callable[[str], bool]) -> tuple[int, str]:
    """The messages of the topics ``exported`` picks: what the export will count, so its
    last progress line reads 100 %; and the note on a recorded config this version cannot
    read ("": none). An export copies what was recorded and never applies the config, so a
    newer dobhil's log is exported (``describe``), with the note ``log info`` gives."""
    from dobhil.recording.reader import open_log, unknown_keys_note

    with open_log(path, describe=True) as log:
        note = unknown_keys_note(log.unknown_config) if log.unknown_config else ""
        return sum(n for topic, n in log.message_counts().items() if exported(topic)), note


def _say_note(note: str) -> None:
    """The note of :func:`_total` on stderr (after the command's checks: bad input stays its one line)."""
    if note:
        sys.stderr.write(f"dobhil log: note: {note}\n")


def _stamp(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).isoformat(timespec="milliseconds")


def _topic_width(topics: Iterable[str]) -> int:
    """The topic column's width: the longest topic's (a several-axis log's prefixed topics,
    ``/axis/left/emulator/truth``, run past 20), at least 20, so the counts stay in a column."""
    return max([20, *(len(t) for t in topics)])


def _info_lines(info: Any) -> Iterator[str]:
    yield f"file:       {info.path}"
    yield f"messages:   {info.message_count}"
    yield f"time:       {_stamp(info.start_ns)} .. {_stamp(info.end_ns)} ({info.duration_s:.3f} s)"
    yield f"stop:       {info.stop_reason or '-'}"
    yield f"encoding:   {info.encoding or '-'}"
    if info.layout != "topics":   # /cycle holds the cycle's topics: what a reader of the file sees them as
        yield (f"layout:     {info.layout} (each /cycle message holds a control cycle's /loop, /controller, "
               "/drive/*, /emulator/truth and the CAN frames after it)")
    axes = info.metadata.get("axes")
    if axes:  # a several-axis log: each axis with its bus (its topics under /axis/<name>)
        bus_of = json.loads(axes.get("bus_of", "{}"))
        yield "axes:       " + ", ".join(f"{n} (bus {bus_of.get(n, '?')})" for n in json.loads(axes.get("names", "[]")))
    if info.dropped is not None:
        yield f"dropped:    {info.dropped}"
    if info.unknown_config_keys:
        from dobhil.recording.reader import unknown_keys_note
        yield f"note:       {unknown_keys_note(info.unknown_config_keys)}"
    yield "channels:"
    width = _topic_width(c.topic for c in info.channels)
    for c in info.channels:
        yield f"  {c.topic:<{width}} {c.message_count:>10}  {c.schema_name} ({c.message_encoding})"
    if info.folded:   # the cycle layout: what its /cycle messages hold, as a reader gets them
        yield "in cycle messages:"
        for topic, count in info.folded.items():
            yield f"  {topic:<{width}} {count:>10}"
    for name, record in info.metadata.items():
        yield f"metadata {name}:"
        yield from (f"  {k} = {v}" for k, v in record.items())
    if info.attachments:
        yield f"attachments: {', '.join(info.attachments)}"


def _cmd_info(args: argparse.Namespace) -> int:
    from dobhil.recording.reader import open_log

    # describe: info only describes the file, so a config of a newer dobhil is a note, not a refusal
    with open_log(args.file, describe=True) as log:
        info = log.info()
    if args.json:
        print(json.dumps(info.to_dict(), indent=2))
    else:
        print("\n".join(_info_lines(info)))
    return 0


def _cmd_recover(args: argparse.Namespace) -> int:
    from dobhil.recording.recover import recover

    with _progress("recover", None) as update:
        report = recover(args.file, args.output, progress=update)
    print(f"recovered {report.message_count} messages to {report.output} ({report.stopped_because})")
    if report.message_count:
        print(f"time: {_stamp(report.start_ns)} .. {_stamp(report.end_ns)} ({report.duration_s:.3f} s)")
    width = _topic_width(topic for topic, _ in report.counts)
    for topic, count in report.counts:
        print(f"  {topic:<{width}} {count:>10}")
    for line in report.problems(_stamp):   # one line per stretch skipped, per channel lost
        print(line)
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    if args.can == (args.topic is not None):
        raise LogFileError("give exactly one of --topic T or --can")
    return _export_can(args) if args.can else _export_topic(args)


def _export_topic(args: argparse.Namespace) -> int:
    from dobhil.recording.convert import default_csv_output, export_csv

    if args.format != "csv":
        raise LogFileError(f"--topic exports only --format csv, got {args.format!r}")
    out = args.output or default_csv_output(args.file, args.topic)
    total, note = _total(args.file, lambda topic: topic == args.topic)
    with _progress("export", total) as update:
        count = export_csv(args.file, args.topic, out, progress=update)
    print(f"wrote {count} rows of {args.topic} to {out}")
    _say_note(note)
    return 0


def _export_can(args: argparse.Namespace) -> int:
    from dobhil.canio.canlog import default_can_output, export_can, parse_format
    from dobhil.canio.frames import is_frame_topic

    fmt = parse_format(args.format)
    out = args.output or default_can_output(args.file, fmt)
    total, note = _total(args.file, is_frame_topic)
    with _progress("export", total) as update:
        count = export_can(args.file, out, fmt, progress=update)
    print(f"wrote {count} CAN frames to {out}")
    _say_note(note)
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from dobhil.canio.canlog import import_can

    def warn(line: str) -> None:
        sys.stderr.write(f"dobhil log: warning: {line}\n")

    with _progress("import", None) as update:
        count = import_can(args.canlog, args.output, progress=update, warn=warn)
    print(f"imported {count} CAN frames to {args.output}")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from dobhil.recording.reader import open_log
    from dobhil.recording.relayout import relayout

    with open_log(args.file, describe=True) as log:
        total = sum(log.message_counts().values())
    with _progress("convert", total) as update:
        done = relayout(args.file, args.layout, args.output, progress=update)
    print(f"wrote {done.messages} messages in the {done.layout} layout to {done.output} "
          f"({done.written} MCAP messages)")
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    from dobhil.live.cli import serve_command

    return serve_command(args.file, live=args.live, speed=args.speed, loop=args.loop)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``dobhil log`` and its sub-subcommands."""
    parser = subparsers.add_parser("log", help="inspect, recover, export and import recordings")
    sub = parser.add_subparsers(dest="log_command", metavar="ACTION")
    sub.required = True
    info = sub.add_parser("info", help="channels, counts, duration, metadata, stop reason")
    info.add_argument("file")
    info.add_argument("--json", action="store_true", help="print JSON")
    info.set_defaults(func=_cmd_info)
    rec = sub.add_parser("recover", help="salvage a recording cut short into a new file")
    rec.add_argument("file")
    rec.add_argument("-o", "--output", type=output_path, help="output (default FILE.recovered.mcap)")
    rec.set_defaults(func=_cmd_recover)
    exp = sub.add_parser("export", help="one topic to CSV, or CAN frames to candump/asc/blf")
    exp.add_argument("file")
    exp.add_argument("--topic", help="topic to export as CSV")
    exp.add_argument("--can", action="store_true", help="export /can/rx and /can/tx frames")
    exp.add_argument("--format", required=True, choices=("csv", "candump", "asc", "blf"))
    exp.add_argument("-o", "--output", type=output_path, help="output file (default next to FILE)")
    exp.set_defaults(func=_cmd_export)
    imp = sub.add_parser("import", help="record a python-can readable CAN log as MCAP")
    imp.add_argument("canlog")
    imp.add_argument("-o", "--output", type=output_path, required=True, help="MCAP file to write")
    imp.set_defaults(func=_cmd_import)
    conv = sub.add_parser("convert", help="copy a recording in the other layout (a message per topic, or per cycle)")
    conv.add_argument("file")
    conv.add_argument("--layout", required=True, choices=LAYOUTS,
                      help="topics: a message per topic (what tools reading topics by name need); cycle: a "
                           "message per control cycle, about a third of the bytes (docs/recording.md)")
    conv.add_argument("-o", "--output", type=output_path, help="output (default FILE.LAYOUT.mcap)")
    conv.set_defaults(func=_cmd_convert)
    srv = sub.add_parser("serve", help="play a recording to Foxglove over WebSocket at its recorded pace")
    srv.add_argument("file")
    srv.add_argument("--live", default="8765", metavar="[HOST:]PORT", help="listen address (default 127.0.0.1:8765)")
    srv.add_argument("--speed", type=float, default=1.0, help="factor of the recorded pace (default 1)")
    srv.add_argument("--loop", action="store_true", help="start over at the end until Ctrl-C "
                     "(a pass lasts 0.5 s at least: a recording of one instant is sent twice a second)")
    srv.set_defaults(func=_cmd_serve)
