"""The ``mit:`` section of a drive profile and what MIT mode asks of the common keys.

Validated by :mod:`dobhil.drives.profile` with the same validator and error style as every
key (``<source>: mit.reply_id: expected an integer from 0 to 2047 ..., got 4096``);
``drivers/README.md`` documents each key. Then the whole profile against its row of the
model table (:func:`check_mit_profile`): the row must exist (``mit.vendor``, ``mit.model``
and the profile's ``firmware``), ``torque_limit`` must lie within the row's torque range
(a command beyond it is clamped by the codec: the controller would believe in torque the
motor never gets), and ``node_id`` must fit where the reply carries it (Damiao: the low
nibble of byte 0, 1..15; the others: byte 0, 1..255). Each refusal is one line.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import MappingProxyType

from dobhil.drives.mit.codec import MitModel
from dobhil.drives.mit.models import find_model
from dobhil.drives.profile import DriveProfile, ProtocolRules, Rule
from dobhil.errors import ConfigError

__all__ = ["MAX_REPLY_ID", "MAX_ZERO_SILENCE", "MIT_RULES", "check_mit_profile", "max_node_id", "model_of"]

#: replies come on a standard (11-bit) id: the firmware's CAN master id
MAX_REPLY_ID = 0x7FF
#: a motor silent for longer than this after set-zero is not zeroing, it is gone
MAX_ZERO_SILENCE = 10.0


def max_node_id(model: MitModel) -> int:
    """The largest node id the reply's id field can carry: 15 in the low nibble of byte 0
    (Damiao: the high nibble is the state), else 255 (all of byte 0)."""
    return model.layout.max_motor_id


def model_of(profile: DriveProfile) -> MitModel:
    """The profile's row of the model table (``mit.models``, relative to the profile's
    directory, or the shipped ``drivers/mit-models.yaml``); ConfigError (one line) when
    there is no such row."""
    opts = profile.options
    table = opts.get("models")
    path: Path | None = None
    if table:
        path = Path(str(table))
        if not path.is_absolute() and profile.directory:
            path = Path(profile.directory) / path
    return find_model(str(opts["vendor"]), str(opts["model"]), profile.firmware, path)


def check_mit_profile(profile: DriveProfile, source: str) -> None:
    """The profile against its model row (see the module's words); ConfigError, one line."""
    try:
        model = model_of(profile)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    name = f"{model.vendor} {model.model} (firmware {model.firmware!r})"
    if profile.torque_limit > model.t_max:
        raise ConfigError(f"{source}: torque_limit: expected a number > 0 and <= {model.t_max:g} Nm (the torque "
                          f"range of the {name} in the model table), got {profile.torque_limit:g}")
    if profile.velocity_limit > model.v_max:
        raise ConfigError(f"{source}: velocity_limit: expected a number > 0 and <= {model.v_max:g} rad/s (the "
                          f"velocity range of the {name} in the model table), got {profile.velocity_limit:g}")
    top = max_node_id(model)
    if not 1 <= profile.node_id <= top:
        where = "the low nibble of reply byte 0" if top == 0x0F else "reply byte 0"
        raise ConfigError(f"{source}: node_id: expected an integer from 1 to {top} for the {name} (the id is "
                          f"{where}), got {profile.node_id}")


MIT_RULES = ProtocolRules(
    section=MappingProxyType({
        "vendor": Rule((str,), "a vendor of the model table, e.g. 'cubemars', 'damiao', 'mini-cheetah'",
                       lambda v: bool(v)),
        "model": Rule((str,), "a model of the model table, e.g. 'AK80-9', 'DM4310'", lambda v: bool(v)),
        "reply_id": Rule((int,), f"an integer from 0 to {MAX_REPLY_ID} (the arbitration id of the motor's "
                         "replies: its CAN master id)", lambda v: 0 <= v <= MAX_REPLY_ID, default=0),
        "models": Rule((str,), "the path of a model table (relative to the profile's directory)",
                       lambda v: bool(v), default=None),
        "zero_silence": Rule((int, float), f"a number from 0 to {MAX_ZERO_SILENCE:g} s (how long the motor is "
                             "silent after set-zero)",
                             lambda v: math.isfinite(v) and 0 <= v <= MAX_ZERO_SILENCE, default=1.0),
    }),
    common=MappingProxyType({
        "node_id": Rule((int,), "an integer from 1 to 255 (MIT: reply byte 0 carries it)", lambda v: 1 <= v <= 0xFF),
    }),
    check=check_mit_profile,
)
