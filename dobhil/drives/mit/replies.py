"""What an MIT reply says to the host, shared by the drive and its preflight probe (the
probe must not import the drive: the drive names its probe).

- :func:`reply_node`: the node a reply carries: byte 0, or its low nibble on a Damiao
  (whose high nibble is the state);
- :func:`state_of`: whether the motor follows torque commands: a Damiao's state nibble
  says it (1 enabled); a CubeMars or Mini-Cheetah reply carries no mode at all;
- :data:`ZERO_COMMAND`: the one frame that never moves a motor (p = v = kp = kd = t = 0),
  the enable's keepalive and the preflight's question;
- :class:`MitFault`: dobhil's own codes for what only the values of a reply say;
- :func:`lost_communication_codes`: the codes by which a motor says its command timeout
  fired (the table's text for it).
"""

from __future__ import annotations

from enum import IntEnum

from dobhil.drives.mit.codec import Command, MitModel, Reply

__all__ = ["DAMIAO_ENABLED", "LOST_COMMUNICATION", "ZERO_COMMAND", "MitFault", "lost_communication_codes",
           "reply_node", "state_of"]

#: the Damiao state nibble of a motor in motor mode
DAMIAO_ENABLED = 1
#: the model table's text of the code a motor reports when its command timeout fired
#: (Damiao state 0xD, damiao-motor's DM_MOTOR_LOST_COMM)
LOST_COMMUNICATION = "communication lost"
#: p = v = kp = kd = t_ff = 0: the motor applies no torque (the keepalive, the probe)
ZERO_COMMAND = Command(position=0.0, velocity=0.0, kp=0.0, kd=0.0, torque=0.0)


class MitFault(IntEnum):
    """dobhil's own error codes for what a reply's bytes say only by their values (above
    any error byte or state nibble a motor sends, so they never collide)."""

    AT_RAIL = 0x100     # a saturating position reading on the end of its range
    BAD_LAYOUT = 0x101  # a reply to us whose length the model's layout lacks


def reply_node(model: MitModel, data: bytes | bytearray) -> int:
    """The node id a reply carries (-1: empty frame): byte 0, or its low nibble (Damiao)."""
    if not data:
        return -1
    return data[0] & 0x0F if model.layout.id_field == "low_nibble0" else data[0]


def state_of(model: MitModel, reply: Reply) -> tuple[bool, str]:
    """(follows torque commands, the state's words) of one reply: a Damiao's state nibble
    says it; a CubeMars or Mini-Cheetah reply carries no mode (a reply means it answers)."""
    if reply.state < 0:
        return True, "answering (the reply carries no mode)"
    if reply.state == DAMIAO_ENABLED:
        return True, "enabled (state 1)"
    if reply.state == 0:
        return False, "disabled (state 0)"
    return False, f"{reply.error_text or 'fault'} (state 0x{reply.state:X})"


def lost_communication_codes(model: MitModel) -> frozenset[int]:
    """The error codes (error byte or state nibble) by which ``model``'s replies say that
    its command timeout fired; empty when its layout has none (a Mini-Cheetah only zeroes
    its command, silently)."""
    layout = model.layout
    return frozenset(code for code, text in (*layout.errors.items(), *layout.states.items())
                     if text == LOST_COMMUNICATION)
