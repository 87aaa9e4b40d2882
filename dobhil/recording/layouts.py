"""How a log lays out its messages, by name (``dobhil run --log-layout``): a module of
names only, so the command line offers them without importing the recording.

- ``topics``: a message per topic per control cycle and one per CAN frame (Foxglove shows
  each topic);
- ``cycle``: one message per control cycle holding the cycle's topics and the frames
  after it (:mod:`dobhil.recording.cycles`): about a third of the bytes.
"""

from __future__ import annotations

from typing import Final

LAYOUTS: Final = ("topics", "cycle")
DEFAULT_LAYOUT: Final = "topics"
#: The topic (after the lane's prefix) and schema of a cycle layout's message.
CYCLE_TOPIC: Final = "/cycle"
CYCLE_SCHEMA: Final = "dobhil.Cycle"

__all__ = ["CYCLE_SCHEMA", "CYCLE_TOPIC", "DEFAULT_LAYOUT", "LAYOUTS"]
