"""The ``moteus:`` section of a drive profile and what moteus asks of the common keys.

Validated by :mod:`dobhil.drives.profile` with the same validator and error style as every
key; ``drivers/README.md`` documents each key. The resolutions are the multiplex
protocol's four types (``docs/protocol/can.md``: int8, int16, int32, float); the node id is
7 bits with 0x7f the broadcast (``docs/protocol/can.md`` "CAN ID"), so 1 to 126.
"""

from __future__ import annotations

from types import MappingProxyType

from dobhil.drives.moteus.codec import MAX_NODE_ID, Resolution
from dobhil.drives.moteus.frames import RESOLUTION_NAMES
from dobhil.drives.profile import DriveProfile, ProtocolRules, Rule

__all__ = ["MAX_PREFIX", "MOTEUS_RULES", "resolution"]

#: ``can.prefix``: the 13 bits above the source, destination and reply bit
MAX_PREFIX = 0x1FFF
_NAMES = ", ".join(RESOLUTION_NAMES)


def _resolution_rule(what: str, default: str) -> Rule:
    return Rule((str,), f"one of {_NAMES} (the {what}'s type on the wire)",
                lambda v: v in RESOLUTION_NAMES, default=default)


def resolution(profile: DriveProfile, key: str) -> Resolution:
    """The profile's resolution ``key`` (validated: one of :data:`RESOLUTION_NAMES`)."""
    return RESOLUTION_NAMES[str(profile.options[key])]


MOTEUS_RULES = ProtocolRules(
    section=MappingProxyType({
        "source_id": Rule((int,), f"an integer from 0 to {MAX_NODE_ID} (the host's id in the arbitration id)",
                          lambda v: 0 <= v <= MAX_NODE_ID, default=0),
        "can_prefix": Rule((int,), f"an integer from 0 to {MAX_PREFIX} (the controller's can.prefix)",
                           lambda v: 0 <= v <= MAX_PREFIX, default=0),
        "position_resolution": _resolution_rule("queried position", "f32"),
        "velocity_resolution": _resolution_rule("queried velocity", "f32"),
        "torque_resolution": _resolution_rule("queried torque", "f32"),
        "command_resolution": _resolution_rule("position-mode command", "f32"),
        "bitrate_switch": Rule((bool,), "true or false (the data phase at the data bit rate)",
                               lambda v: True, default=True),
    }),
    common=MappingProxyType({
        "node_id": Rule((int,), f"an integer from 1 to {MAX_NODE_ID} (moteus: 7-bit id, 0x7f is the broadcast)",
                        lambda v: 1 <= v <= MAX_NODE_ID),
    }),
)
