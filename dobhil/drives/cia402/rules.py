"""The ``cia402:`` section of a drive profile and what CiA 402 asks of the common keys.

Validated by :mod:`dobhil.drives.profile` with the same validator and error style as every
key (``<source>: cia402.rated_torque_unit: expected one of 'mNm', 'uNm', got 'Nm'``);
``drivers/README.md`` documents each key. Pure: no canopen, so a profile loads without it.
"""

from __future__ import annotations

import math
from types import MappingProxyType
from typing import Any

from dobhil.drives.profile import DriveProfile, Rule, ProtocolRules
from dobhil.errors import ConfigError

__all__ = ["CIA402_RULES", "RATED_TORQUE_UNITS", "VELOCITY_UNITS"]

#: the unit of 0x6076 on a drive: mNm per CiA 402, uNm on a maxon EPOS4
RATED_TORQUE_UNITS = ("mNm", "uNm")
#: the unit of 0x606C velocity actual
VELOCITY_UNITS = ("rpm", "increments_per_s", "milli_rpm")
#: the pre-defined connection set has four PDOs each way; the motion TPDO is tpdo + 1
MAX_RPDO, MAX_TPDO = 4, 3
#: SDO answers: a node answers within milliseconds; 10 s is a unit mistake
MAX_SDO_TIMEOUT = 10.0
#: SYNC periods the enable needs at the least: the first statusword (a TPDO answers a SYNC),
#: then one for each of the power state machine's transitions shutdown, switch on and enable
#: operation (CiA 402; each controlword is answered by the statusword of a later SYNC)
ENABLE_SYNCS = 4


def _positive(limit: float) -> Any:
    return lambda v: math.isfinite(v) and 0 < v <= limit


def _whole_ms(seconds: float) -> bool:
    return abs(seconds * 1e3 - round(seconds * 1e3)) < 1e-6


def _one_of(values: tuple[str, ...]) -> str:
    return "one of " + ", ".join(repr(v) for v in values)


def check_cia402_profile(profile: DriveProfile, source: str) -> None:
    """Cross-key checks, once every key passed its rule (and with a config's
    ``drive.node_id`` in place of the profile's): an ``enable_timeout`` shorter than
    :data:`ENABLE_SYNCS` SYNC periods never enables; a node watching the host
    (``consumer_heartbeat`` > 0) hears it on 0x700 + ``host_node_id`` (CiA 301's heartbeat
    COB-ID), which is the node's own heartbeat when the two ids are one. Checked here, where
    the profile is read, so ``dobhil check``, ``analyze`` and ``emulate`` refuse it as ``dobhil
    run`` does, before any bus opens."""
    sync = profile.feedback_period or 0.0
    if profile.enable_timeout < ENABLE_SYNCS * sync * (1 - 1e-9):
        raise ConfigError(f"{source}: enable_timeout: expected at least {ENABLE_SYNCS} SYNC periods "
                          f"({ENABLE_SYNCS * sync:g} s: the first statusword, then one per transition of the "
                          f"power state machine), got {profile.enable_timeout:g}")
    node, host = profile.node_id, int(profile.options["host_node_id"])
    if host == node and float(profile.options["consumer_heartbeat"]) > 0:
        raise ConfigError(f"{source}: cia402.host_node_id: expected an id other than the node's ({node}): "
                          f"the host's heartbeat 0x{0x700 + node:03X} would be the node's own")


CIA402_RULES = ProtocolRules(
    section=MappingProxyType({
        "eds": Rule((str,), "the node's EDS file (relative to the profile's directory, or a path)",
                    lambda v: bool(v)),
        "rated_torque": Rule((int, float), "a number > 0 and <= 10000 Nm (the motor's rated torque, "
                             "0x6076 after rated_torque_unit)", _positive(1e4)),
        "rated_torque_unit": Rule((str,), _one_of(RATED_TORQUE_UNITS), lambda v: v in RATED_TORQUE_UNITS,
                                  default="mNm"),
        # 0x608F:01 (encoder increments) is an UNSIGNED32: a fraction could never be set on the node
        "position_per_rev": Rule((int,), "an integer from 1 to 4294967295 (increments of 0x6064 per motor "
                                 "revolution, as 0x608F:01 holds them)", lambda v: 1 <= v <= 0xFFFFFFFF),
        "velocity_unit": Rule((str,), _one_of(VELOCITY_UNITS), lambda v: v in VELOCITY_UNITS,
                              default="rpm"),
        "gear_ratio": Rule((int, float), "a number > 0 (motor turns per output turn)", _positive(1e6),
                           default=1.0),
        "rpdo": Rule((int,), f"an RPDO number from 1 to {MAX_RPDO}", lambda v: 1 <= v <= MAX_RPDO,
                     default=1),
        "tpdo": Rule((int,), f"a TPDO number from 1 to {MAX_TPDO} (the motion TPDO is the next one)",
                     lambda v: 1 <= v <= MAX_TPDO, default=1),
        "sdo_timeout": Rule((int, float), f"a number > 0 and <= {MAX_SDO_TIMEOUT:g} s",
                            _positive(MAX_SDO_TIMEOUT), default=0.3),
        # 0x1016 holds the time in whole ms: any other value would reach the node rounded,
        # up to 0.5 ms shorter than the watch the host's checks and heartbeat are made for
        "consumer_heartbeat": Rule((int, float), "0 (off) or a whole number of milliseconds from 0.004 to 60 s "
                                   "(the node's heartbeat consumer time 0x1016 on the host, in ms)",
                                   lambda v: math.isfinite(v) and (v == 0 or (4e-3 <= v <= 60.0 and _whole_ms(v))),
                                   default=0.0),
        "host_node_id": Rule((int,), "an integer from 1 to 127 (the node id of the host's heartbeat "
                             "0x700 + id, for consumer_heartbeat)", lambda v: 1 <= v <= 127, default=127),
    }),
    common=MappingProxyType({
        "node_id": Rule((int,), "an integer from 1 to 127 (CANopen node id)", lambda v: 1 <= v <= 127),
    }),
    requires=frozenset({"feedback_period"}),
    check=check_cia402_profile,
)
