"""Drive profiles: one frozen :class:`DriveProfile` per YAML file under ``drivers/``.

``load_profile(name_or_path)`` accepts a path to a YAML file, or a profile name looked
up as ``<name>.yaml`` in the nearest ``drivers/`` directory above ``near`` (the config's
directory: the layout of the repository and of ``dobhil init``), then among the shipped
profiles (``drivers/`` of the repository, installed as ``dobhil.data.drivers``; see
:mod:`dobhil.data`). Every key is documented in ``drivers/README.md``. Validation is
protocol-neutral; each protocol checks its own values (e.g. ODrive firmware and node id
range) when the drive is made.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any

import yaml

from dobhil.config.schema import Config
from dobhil.config.yamlio import TextFileError, read_text_file, safe_load, show_value, where
from dobhil.errors import ConfigError

__all__ = ["DriveProfile", "default_drivers_dir", "load_drive_profile", "load_profile", "profile_from_mapping"]


@dataclass(frozen=True, kw_only=True)
class DriveProfile:
    """What the host must know about one drive. Times in s, torques in Nm, speeds in rad/s."""

    protocol: str  # implementation name, e.g. "odrive"
    firmware: str  # protocol-specific version string, e.g. "0.6"
    node_id: int
    torque_limit: float  # [Nm] drive-side clamp (emulator) and controller bound
    velocity_limit: float  # [rad/s]
    encoder_msg_rate: float  # [s] period of cyclic position/velocity frames
    heartbeat_msg_rate: float  # [s] period of cyclic status frames
    watchdog_timeout: float  # [s] drive-side command watchdog; 0 disables it
    enable_timeout: float  # [s] default wait of Drive.enable()
    bus: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}), hash=False)
    name: str = ""  # where the profile came from (file stem), for messages
    #: the protocol applies each command this many loop periods after its sample (None: not set)
    command_delay_periods: int | None = None

    def __post_init__(self) -> None:
        # the bounds hold for a profile built in code too (dataclasses.replace, tests):
        # the emulator and the waits rely on them
        for key in _BOUNDED:
            _check_value(key, getattr(self, key), f"drive profile {self.name or self.protocol!r}")

    def bus_kwargs(self) -> dict[str, Any]:
        """Extra keyword arguments for ``can.Bus(...)`` (interface, channel, bitrate, ...)."""
        return dict(self.bus)


def _within(low: float, high: float, unit: str) -> tuple[str, Any]:
    return (f"a number from {low:g} to {high:g} {unit}",
            lambda v: math.isfinite(v) and low <= v <= high)


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

# key -> (accepted types, description of allowed values, check)
_RULES: Mapping[str, tuple[tuple[type, ...], str, Any]] = MappingProxyType({
    "protocol": ((str,), "a protocol name such as 'odrive'", lambda v: bool(v)),
    "firmware": ((str,), "a quoted version string such as '0.6'", lambda v: bool(v)),
    "node_id": ((int,), f"an integer from 0 to {MAX_NODE_ID} (29-bit CAN id)",
                lambda v: 0 <= v <= MAX_NODE_ID),
    "torque_limit": ((int, float), f"a number > 0 and <= {MAX_TORQUE:g} Nm",
                     lambda v: math.isfinite(v) and 0 < v <= MAX_TORQUE),
    "velocity_limit": ((int, float), f"a number > 0 and <= {MAX_VELOCITY:g} rad/s",
                       lambda v: math.isfinite(v) and 0 < v <= MAX_VELOCITY),
    "encoder_msg_rate": ((int, float), *_within(MIN_FRAME_PERIOD, MAX_FRAME_PERIOD, "s")),
    "heartbeat_msg_rate": ((int, float), *_within(MIN_HEARTBEAT, MAX_FRAME_PERIOD, "s")),
    "watchdog_timeout": ((int, float), f"0 (off) or a number from {MIN_HEARTBEAT:g} to {MAX_WAIT:g} s",
                         lambda v: math.isfinite(v) and (v == 0 or MIN_HEARTBEAT <= v <= MAX_WAIT)),
    "enable_timeout": ((int, float), *_within(MIN_HEARTBEAT, MAX_WAIT, "s")),
    "bus": ((dict,), "a mapping of can.Bus keyword arguments", lambda v: all(isinstance(k, str) for k in v)),
    "name": ((str,), "a string", lambda v: True),
    "command_delay_periods": ((int,), "an integer from 0 to 20", lambda v: 0 <= v <= 20),
})
_OPTIONAL = frozenset({"bus", "name", "command_delay_periods"})
_BOUNDED = ("node_id", "torque_limit", "velocity_limit", "encoder_msg_rate", "heartbeat_msg_rate",
            "watchdog_timeout", "enable_timeout")


def default_drivers_dir() -> Path:
    """The shipped profiles (``drivers/`` of the repository, ``dobhil.data.drivers`` installed)."""
    from dobhil.data import drivers_dir
    return drivers_dir()


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False for a name the file system cannot even look up (too long)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except (OSError, ValueError):
        return False


def _near(name: str, near: Path) -> Path | None:
    """``drivers/<name>.yaml`` in ``near`` or the closest of its parents that has one."""
    start = near.resolve()
    for directory in (start, *start.parents):
        path = directory / "drivers" / f"{name}.yaml"
        if _is_file(path):
            return path
    return None


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


def _check_value(key: str, value: Any, source: str) -> Any:
    types, allowed, ok = _RULES[key]
    if float in types:
        value = _as_number(value)
    type_ok = isinstance(value, types) and not isinstance(value, bool)
    if not type_ok or not ok(value):
        raise ConfigError(f"{source}: {key}: expected {allowed}, got {show_value(value)}")
    if float in types:
        return float(value)
    if key == "bus":
        return MappingProxyType(dict(value))
    return value


def profile_from_mapping(data: Mapping[str, Any], *, source: str = "<profile>") -> DriveProfile:
    """Validate a mapping and build a DriveProfile; ConfigError names key, value and rule."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a mapping of profile keys, got {type(data).__name__}")
    allowed = ", ".join(_RULES)
    for key in data:
        if key not in _RULES:
            raise ConfigError(f"{source}: unknown key {key!r} (allowed: {allowed})")
    for f in fields(DriveProfile):
        if f.name not in data and f.name not in _OPTIONAL:
            raise ConfigError(f"{source}: missing key {f.name!r} ({_RULES[f.name][1]})")
    values = {key: _check_value(key, value, source) for key, value in data.items()}
    return DriveProfile(**values)


def _resolve(name_or_path: str | os.PathLike[str], drivers_dir: Path | None, near: Path | None) -> Path:
    text = os.fspath(name_or_path)
    candidate = Path(text)
    if candidate.suffix in (".yaml", ".yml") or os.sep in text or "/" in text:
        if _exists(candidate):
            return candidate  # a directory, FIFO or device is refused, with its reason, when read
        raise ConfigError(f"profile file {text!r} does not exist")
    found = _near(text, near) if near is not None and drivers_dir is None else None
    if found is not None:
        return found
    directory = drivers_dir if drivers_dir is not None else default_drivers_dir()
    path = directory / f"{text}.yaml"
    if _is_file(path):
        return path
    known = sorted(p.stem for p in directory.glob("*.yaml")) if directory.is_dir() else []
    hint = f"in {directory}" if drivers_dir is not None else \
        f"(shipped), or {text}.yaml in a drivers/ directory above the config, or a path to a .yaml file"
    raise ConfigError(f"drive profile {text!r}: expected one of {known} {hint}")


def load_profile(
    name_or_path: str | os.PathLike[str], *, drivers_dir: Path | None = None, near: Path | None = None
) -> DriveProfile:
    """Load a profile by name (from ``drivers_dir``, else a ``drivers/`` above ``near``, else the
    shipped ones) or an explicit YAML path into a DriveProfile."""
    path = _resolve(name_or_path, drivers_dir, near)
    try:
        data = safe_load(read_text_file(path))
    except TextFileError as exc:
        raise ConfigError(f"{path}: cannot read drive profile: it {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: YAML error in drive profile{where(exc)}") from None
    except (OSError, ValueError, RecursionError) as exc:
        raise ConfigError(f"{path}: cannot read drive profile: {' '.join(str(exc).split())}") from None
    data = {"name": path.stem, **(data or {})} if isinstance(data, Mapping) else data
    return profile_from_mapping(data, source=str(path))


def load_drive_profile(config: Config, base_dir: Path | None = None) -> DriveProfile:
    """The profile ``drive.profile`` of ``config`` names: a YAML file relative to ``base_dir``
    (the config's directory) if there is one, else a profile name looked up near it."""
    name = config.drive.profile
    candidate = (base_dir / name) if base_dir and not Path(name).is_absolute() else Path(name)
    return load_profile(str(candidate) if candidate.suffix in (".yaml", ".yml") and candidate.exists()
                        else name, near=base_dir)
