"""Drive profiles: one frozen :class:`DriveProfile` per YAML file under ``drivers/``, and
the one validator that builds it. Files are read by :mod:`dobhil.drives.load`
(``load_profile``), which passes the registry's protocols to this validator. Every key is
documented in ``drivers/README.md``.

A profile has the common keys (:data:`COMMON_RULES`) and, under the key named after its
protocol (``odrive:``, ``cia402:``), a section of that protocol's own settings. One
validator checks both, with one error style (``<source>: <key>: expected <allowed>, got
<value>``): the protocol's :class:`ProtocolRules` -- ``Drive.profile_rules`` of the
protocol's drive class, handed to :func:`profile_from_mapping` in a
:class:`ProtocolLookup` (the registry's, by :mod:`dobhil.drives.load`) -- say which keys
its section has, how it narrows common keys (an ODrive node id has 6 bits) and which
optional common keys it needs (an ODrive streams feedback and heartbeats, so it needs
both periods). The validated section is
:attr:`DriveProfile.options`, read-only, its defaults filled in.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

from dobhil.config.yamlio import show_value
from dobhil.errors import ConfigError

__all__ = [
    "COMMON_RULES",
    "REQUIRED",
    "RENAMED_KEYS",
    "DriveProfile",
    "ProtocolLookup",
    "ProtocolRules",
    "Rule",
    "default_drivers_dir",
    "profile_from_mapping",
]


class _Required:
    """The type of :data:`REQUIRED` (a sentinel: ``None`` is a real default)."""

    def __repr__(self) -> str:
        return "REQUIRED"


#: ``Rule.default`` of a key that must be given
REQUIRED: Final = _Required()

_EMPTY: Mapping[str, Any] = MappingProxyType({})


#: the bit rates a profile's ``bus`` may give python-can and their ceilings: the nominal rate
#: (classic CAN, and CAN FD's arbitration phase) is at most 1 Mbit/s (ISO 11898-1); a CAN FD
#: data phase runs at up to 8-12 Mbit/s, and twice that leaves room and catches a typo's 1e300
MAX_NOMINAL_RATE = 1_000_000
MAX_BUS_RATE = 25_000_000
_BUS_RATES = {"bitrate": MAX_NOMINAL_RATE, "data_bitrate": MAX_BUS_RATE}


def _bus_arguments(value: Mapping[Any, Any]) -> bool:
    """Text keys; a bit rate, where given, a whole number of bit/s the interface can take
    (a rate of "abc" or -5 would reach the interface's constructor, or the bus budget); a
    CAN FD data phase no slower than the nominal one (ISO 11898-1: bit rate switching only
    speeds the data phase up; a slower one would make the bus budget count FD frames as
    longer than the same classic ones)."""
    rates_ok = all(isinstance(k, str) for k in value) and all(
        type(value[r]) is int and 1 <= value[r] <= top for r, top in _BUS_RATES.items() if r in value)
    if not rates_ok or "data_bitrate" not in value:
        return rates_ok
    return bool(value["data_bitrate"] >= value.get("bitrate", 0))


@dataclass(frozen=True)
class Rule:
    """What one profile key accepts: its types, the allowed values in words (the error
    message's ``expected ...``), the check of a value of the right type, and its default
    (:data:`REQUIRED`: it must be given; ``None``: optional and unset when absent).

    A number key (``float`` in ``types``) reads a string as YAML 1.2 does (``1e-9`` is a
    number) and gives a float; a ``bool`` is never an int or a float unless ``types``
    names ``bool``; a ``dict`` key gives a read-only mapping."""

    types: tuple[type, ...]
    allowed: str
    check: Callable[[Any], bool]
    default: Any = REQUIRED

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    @classmethod
    def number(cls, low: float, high: float, unit: str, default: Any = REQUIRED) -> Rule:
        """A finite number from ``low`` to ``high`` (inclusive), e.g. a period in s."""
        return cls((int, float), f"a number from {low:g} to {high:g} {unit}".rstrip(),
                   lambda v: math.isfinite(v) and low <= v <= high, default)

    @classmethod
    def integer(cls, low: int, high: int, default: Any = REQUIRED) -> Rule:
        """An integer from ``low`` to ``high`` (inclusive)."""
        return cls((int,), f"an integer from {low} to {high}", lambda v: low <= v <= high, default)

    @classmethod
    def one_of(cls, *choices: Any, default: Any = REQUIRED) -> Rule:
        """One of ``choices`` (all of one type), e.g. a unit name."""
        types = tuple(sorted({type(c) for c in choices}, key=lambda t: t.__name__))
        return cls(types, "one of " + ", ".join(repr(c) for c in choices), lambda v: v in choices, default)

    def validate(self, key: str, value: Any, source: str) -> Any:
        """``value`` as the profile keeps it; ConfigError (one line) naming ``key``, what is
        allowed and ``value`` when the rule refuses it."""
        if value is None and self.default is None:
            return None  # an optional key left empty (``key:`` in YAML) is unset
        numeric = float in self.types
        if numeric:
            value = _as_number(value)
        type_ok = isinstance(value, self.types) and (bool in self.types or not isinstance(value, bool))
        if not type_ok or not _passes(self.check, value):
            raise ConfigError(f"{source}: {key}: expected {self.allowed}, got {show_value(value)}")
        if numeric and not isinstance(value, bool):
            return float(value)
        if isinstance(value, dict):
            return MappingProxyType(dict(value))
        return value


def _passes(check: Callable[[Any], bool], value: Any) -> bool:
    """A check that raises on an odd value (a comparison of a huge int) refuses it."""
    try:
        return bool(check(value))
    except (TypeError, ValueError, OverflowError, ArithmeticError):
        return False


@dataclass(frozen=True)
class ProtocolRules:
    """A protocol's part of profile validation (``Drive.profile_rules``).

    - ``section``: the keys of its section (the mapping under the protocol's name);
      an unknown key there is refused, a missing one gets its rule's default.
    - ``common``: narrower rules for common keys (checked after the common rule), e.g.
      ODrive's node id 0..63; the message names the protocol's rule.
    - ``requires``: optional common keys this protocol needs (ODrive: ``feedback_period``,
      ``heartbeat_period``).
    - ``check``: a check of the whole profile once every key passed its own rule, for what
      one key cannot say alone (MIT: ``torque_limit`` within the model's range, which the
      ``mit.model`` row of the model table gives); raises ConfigError (one line, its
      ``source`` first). None: nothing more to check."""

    section: Mapping[str, Rule] = field(default_factory=lambda: _EMPTY)
    common: Mapping[str, Rule] = field(default_factory=lambda: _EMPTY)
    requires: frozenset[str] = frozenset()
    check: Callable[[DriveProfile, str], None] | None = None


# Physically meaningful bounds (drivers/README.md says why each): a value outside them is
# a typo or a unit mistake, and some would hang a run -- a heartbeat every 1e-9 s makes
# the lockstep emulator emit a million frames per simulated millisecond, an enable
# timeout of 1e300 s waits forever.
#: CAN arbitration ids have 29 bits at most (extended frames)
MAX_NODE_ID = (1 << 29) - 1
#: no CAN frame, CAN FD included, is shorter on the wire than ~20 us
MIN_FRAME_PERIOD = 1e-5
#: a status frame is a liveness signal: faster than 1 kHz tells nothing more
MIN_HEARTBEAT = 1e-3
#: slower cyclic frames than this would leave a drive unwatched for too long
MAX_FRAME_PERIOD = 10.0
#: waits for a drive (enable, watchdog): a minute is longer than any drive takes
MAX_WAIT = 60.0
#: torque and speed bounds: beyond any servo drive on CAN (a unit mistake)
MAX_TORQUE = 1e4
MAX_VELOCITY = 1e4
#: a protocol that delays each command by more loop periods than this is not a loop
#: for force control (and the sampled analysis' state grows with it)
MAX_COMMAND_DELAY = 16

#: the common keys, in the order of the README's table; each protocol's drive class
#: may narrow them (``ProtocolRules.common``) and require the optional ones it needs
COMMON_RULES: Mapping[str, Rule] = MappingProxyType({
    "protocol": Rule((str,), "a protocol name such as 'odrive'", lambda v: bool(v)),
    "firmware": Rule((str,), "a quoted version string such as '0.6'", lambda v: bool(v)),
    "node_id": Rule((int,), f"an integer from 0 to {MAX_NODE_ID} (29-bit CAN id)",
                    lambda v: 0 <= v <= MAX_NODE_ID),
    "torque_limit": Rule((int, float), f"a number > 0 and <= {MAX_TORQUE:g} Nm",
                         lambda v: math.isfinite(v) and 0 < v <= MAX_TORQUE),
    "velocity_limit": Rule((int, float), f"a number > 0 and <= {MAX_VELOCITY:g} rad/s",
                           lambda v: math.isfinite(v) and 0 < v <= MAX_VELOCITY),
    "feedback_period": Rule.number(MIN_FRAME_PERIOD, MAX_FRAME_PERIOD, "s", default=None),
    "heartbeat_period": Rule.number(MIN_HEARTBEAT, MAX_FRAME_PERIOD, "s", default=None),
    "watchdog_timeout": Rule((int, float), f"0 (off) or a number from {MIN_HEARTBEAT:g} to {MAX_WAIT:g} s",
                             lambda v: math.isfinite(v) and (v == 0 or MIN_HEARTBEAT <= v <= MAX_WAIT), 0.0),
    "enable_timeout": Rule.number(MIN_HEARTBEAT, MAX_WAIT, "s"),
    "command_delay_periods": Rule.integer(0, MAX_COMMAND_DELAY, default=None),
    "bus": Rule((dict,), f"a mapping of can.Bus keyword arguments (its bitrate: a whole number from 1 to "
                f"{MAX_NOMINAL_RATE} bit/s, the nominal rate of classic CAN and CAN FD; its data_bitrate: a "
                f"whole number from 1 to {MAX_BUS_RATE} bit/s, at least its bitrate)", _bus_arguments, _EMPTY),
    "name": Rule((str,), "a string", lambda v: True, ""),
})

#: keys of older profiles -> their new names (refused with one line naming the new one:
#: ``encoder_msg_rate`` was never a rate but a period in seconds)
RENAMED_KEYS: Mapping[str, str] = MappingProxyType({
    "encoder_msg_rate": "feedback_period",
    "heartbeat_msg_rate": "heartbeat_period",
})

_BOUNDED = ("node_id", "torque_limit", "velocity_limit", "feedback_period", "heartbeat_period",
            "watchdog_timeout", "enable_timeout", "command_delay_periods")


@dataclass(frozen=True, kw_only=True)
class DriveProfile:
    """What the host must know about one drive. Times in s, torques in Nm, speeds in rad/s."""

    protocol: str  # implementation name, e.g. "odrive"
    firmware: str  # protocol-specific version string, e.g. "0.6"
    node_id: int
    torque_limit: float  # [Nm] drive-side clamp (emulator) and controller bound
    velocity_limit: float  # [rad/s]
    enable_timeout: float  # [s] default wait of Drive.enable()
    watchdog_timeout: float = 0.0  # [s] drive-side command watchdog; 0 disables it
    #: [s] period of the drive's cyclic motion feedback (ODrive encoder estimates; CiA 402
    #: the SYNC period); None: the protocol does not stream feedback on its own
    feedback_period: float | None = None
    #: [s] period of the drive's status / heartbeat frames; None: no heartbeat watched
    heartbeat_period: float | None = None
    #: loop periods after its feedback sample that the protocol itself applies a command
    #: (CiA 402 synchronous RPDO: 1); None: not fixed by the protocol
    command_delay_periods: int | None = None
    bus: Mapping[str, Any] = field(default_factory=lambda: _EMPTY, hash=False)
    name: str = ""  # where the profile came from (file stem), for messages
    #: the protocol's section (``odrive:``, ``cia402:``), validated, defaults filled in
    options: Mapping[str, Any] = field(default_factory=lambda: _EMPTY, hash=False)
    #: the directory of the file it was read from ("" when built in code or from a log):
    #: a section's relative paths (``cia402.eds``) are relative to it
    directory: str = ""

    def __post_init__(self) -> None:
        # the bounds hold for a profile built in code too (dataclasses.replace, tests):
        # the emulator and the waits rely on them
        source = f"drive profile {self.name or self.protocol!r}"
        for key in _BOUNDED:
            COMMON_RULES[key].validate(key, getattr(self, key), source)
        # read-only whatever the caller passed (a dict in code)
        for key in ("bus", "options"):
            value = getattr(self, key)
            if not isinstance(value, MappingProxyType):
                object.__setattr__(self, key, MappingProxyType(dict(value)))

    def bus_kwargs(self) -> dict[str, Any]:
        """Extra keyword arguments for ``can.Bus(...)`` (interface, channel, bitrate, ...)."""
        return dict(self.bus)

    def __reduce__(self) -> tuple[Any, ...]:
        # pickled to the emulator's process: a read-only mapping cannot be pickled, so
        # the mappings travel as dicts and __post_init__ makes them read-only again
        values = {f.name: _plain(getattr(self, f.name)) for f in fields(self)}
        return (_rebuild, (values,))


def _plain(value: Any) -> Any:
    """``value`` with every read-only mapping in it made a dict (picklable)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _rebuild(values: dict[str, Any]) -> DriveProfile:
    return DriveProfile(**values)


def default_drivers_dir() -> Path:
    """The shipped profiles (``drivers/`` of the repository, ``dobhil.data.drivers`` installed)."""
    from dobhil.data import drivers_dir
    return drivers_dir()


def _as_number(value: Any) -> Any:
    """A number key's value as YAML 1.2 reads it: ``1e-9`` (a string to PyYAML's YAML 1.1)
    becomes a float; an integer too large for a float becomes inf (rejected as not finite)."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 1000:
        return math.inf
    return value


@dataclass(frozen=True)
class ProtocolLookup:
    """How the validator finds protocols: ``rules(name)`` gives a protocol's
    :class:`ProtocolRules` (a ConfigError, one line, for an unknown or broken one) and
    ``names()`` every protocol a profile may name. The registry's
    (:data:`dobhil.drives.registry.PROFILE_LOOKUP`) is what :mod:`dobhil.drives.load`
    passes; a test may pass its own. Passed in, not imported: the registry imports the drive
    classes, which import this module."""

    rules: Callable[[str], ProtocolRules]
    names: Callable[[], tuple[str, ...]]


def _protocol_rules(protocols: ProtocolLookup, protocol: str, source: str) -> ProtocolRules:
    """The rules of ``protocol`` (its module is imported only now, when a profile of it is read)."""
    try:
        return protocols.rules(protocol)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _check_keys(data: Mapping[str, Any], protocol: str, known: tuple[str, ...], source: str) -> None:
    """Unknown keys (a section of another protocol told apart), then missing ones."""
    for key in data:
        if key in COMMON_RULES or key == protocol:
            continue
        if isinstance(key, str) and key in known:
            raise ConfigError(f"{source}: {key}: a section of protocol {key!r}, but this profile's "
                              f"protocol is {protocol!r} (its section is {protocol}:)")
        allowed = ", ".join((*COMMON_RULES, protocol))
        raise ConfigError(f"{source}: unknown key {show_value(key)} (allowed: {allowed})")
    for key, rule in COMMON_RULES.items():
        if key not in data and rule.required:
            raise ConfigError(f"{source}: missing key {key!r} ({rule.allowed})")


def _section(value: Any, protocol: str, rules: ProtocolRules, source: str) -> Mapping[str, Any]:
    """The protocol's section validated by its rules, defaults filled in, read-only."""
    if value is None:
        value = {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{source}: {protocol}: expected a mapping of {protocol} settings "
                          f"({', '.join(rules.section) or 'none defined'}), got {show_value(value)}")
    for key in value:
        if key not in rules.section:
            allowed = ", ".join(rules.section) or "none"
            raise ConfigError(f"{source}: unknown key {show_value(f'{protocol}.{key}')} "
                              f"(allowed in {protocol}: {allowed})")
    options: dict[str, Any] = {}
    for key, rule in rules.section.items():
        if key in value:
            options[key] = rule.validate(f"{protocol}.{key}", value[key], source)
        elif rule.required:
            raise ConfigError(f"{source}: missing key '{protocol}.{key}' ({rule.allowed})")
        else:
            options[key] = rule.default
    return MappingProxyType(options)


def profile_from_mapping(data: Mapping[str, Any], *, protocols: ProtocolLookup, source: str = "<profile>",
                         directory: str = "") -> DriveProfile:
    """Validate a mapping and build a DriveProfile; ConfigError names key, value and rule.
    ``protocols``: where the protocols' rules come from (the registry's:
    :func:`dobhil.drives.load.profile_from_mapping`); ``directory``: where the profile's file
    is (for a section's relative paths)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a mapping of profile keys, got {type(data).__name__}")
    for old, new in RENAMED_KEYS.items():
        if old in data:
            raise ConfigError(f"{source}: {old}: renamed to {new} (a period in seconds)")
    if "protocol" not in data:
        raise ConfigError(f"{source}: missing key 'protocol' ({COMMON_RULES['protocol'].allowed})")
    protocol = COMMON_RULES["protocol"].validate("protocol", data["protocol"], source)
    rules = _protocol_rules(protocols, protocol, source)
    _check_keys(data, protocol, protocols.names(), source)
    values: dict[str, Any] = {}
    for key, rule in COMMON_RULES.items():
        if key not in data:
            continue
        values[key] = rule.validate(key, data[key], source)
        narrower = rules.common.get(key)
        if narrower is not None and values[key] is not None:
            values[key] = narrower.validate(key, values[key], source)
    for key in sorted(rules.requires):
        if values.get(key) is None:  # absent, or left empty
            raise ConfigError(f"{source}: missing key {key!r} ({COMMON_RULES[key].allowed}; "
                              f"protocol {protocol!r} needs it)")
    values["options"] = _section(data.get(protocol), protocol, rules, source)
    profile = DriveProfile(**values, directory=directory)
    if rules.check is not None:
        rules.check(profile, source)
    return profile
