#!/usr/bin/env python3
"""Writes ``tools/foxglove-layout.json``, the Foxglove layout for logs in the cycle layout
(the default; ``--log-layout cycle``), whose cycle topics are fields of one ``/cycle``
message (``/cycle.controller.tau_int_hat``; docs/recording.md, Layouts), from
``tools/foxglove-layout-topics.json`` (the topics layout's paths, ``/controller.tau_int_hat``).
The topics layout's file is the one edited by hand (a path there is a topic and a field, as
Foxglove's panels name them); this one is made from it, so the two show the same panels
(``tests/recording/test_report.py`` checks that the shipped file is what this writes).

    python tools/foxglove_layout_cycle.py          # rewrites the file
    python tools/foxglove_layout_cycle.py --check  # exit 1 when the shipped file differs
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dobhil.recording.cycles import FOLDED, field_name  # noqa: E402
from dobhil.recording.layouts import CYCLE_TOPIC  # noqa: E402
from dobhil.recording.schemas import TOPIC_SPECS  # noqa: E402

SOURCE = ROOT / "tools" / "foxglove-layout-topics.json"
TARGET = ROOT / "tools" / "foxglove-layout.json"


def cycle_path(path: str) -> str:
    """A message path of the topics layout as the cycle layout's: ``/loop.exec_time`` ->
    ``/cycle.loop.exec_time``; a topic no cycle message holds (``/events``) as it was."""
    topic, dot, rest = path.partition(".")
    for folded in FOLDED:
        if TOPIC_SPECS[folded].name == topic:
            return f"{CYCLE_TOPIC}.{field_name(folded)}{dot}{rest}"
    return path


def converted(layout: Any) -> Any:
    """``layout`` with every plot and state-transition path in the cycle layout's form."""
    out = json.loads(json.dumps(layout))
    for key, config in out["configById"].items():
        if key.startswith(("Plot!", "StateTransitions!")):
            for p in config["paths"]:
                p["value"] = cycle_path(p["value"])
    return out


def text() -> str:
    return json.dumps(converted(json.loads(SOURCE.read_text())), indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when the shipped file is not what this writes")
    args = parser.parse_args(argv)
    if args.check:
        return 0 if TARGET.exists() and TARGET.read_text() == text() else 1
    TARGET.write_text(text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
