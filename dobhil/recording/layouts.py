"""How a log lays out its messages, by name (``dobhil run --log-layout``): a module of
names only, so the command line offers them without importing the recording.

- ``cycle`` (the default): one message per control cycle holding the cycle's topics and
  the frames after it (:mod:`dobhil.recording.cycles`): a third of the topics layout's bytes
  and half its writer CPU, read back by dobhil, python-can and Foxglove alike;
- ``topics``: a message per topic per control cycle and one per CAN frame, for tools that
  read a topic by its name (docs/recording.md, Layouts).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:   # only for the annotations: this module imports nothing of the recording
    from mcap.records import Channel, Schema

LAYOUTS: Final = ("topics", "cycle")
DEFAULT_LAYOUT: Final = "cycle"
#: The topic (after the lane's prefix) and schema of a cycle layout's message.
CYCLE_TOPIC: Final = "/cycle"
CYCLE_SCHEMA: Final = "dobhil.Cycle"



def cycle_lane(schema: Schema | None, channel: Channel) -> str | None:
    """The lane prefix (``""``, ``/axis/<name>``) of a channel holding cycle messages, or
    None for any other channel (``schema``: the channel's, None when it has none): one test
    for the readers' and recover's views."""
    if schema is not None and schema.name == CYCLE_SCHEMA and channel.topic.endswith(CYCLE_TOPIC):
        return channel.topic[:-len(CYCLE_TOPIC)]
    return None


__all__ = ["CYCLE_SCHEMA", "CYCLE_TOPIC", "DEFAULT_LAYOUT", "LAYOUTS", "cycle_lane"]
