"""Load and validate configurations: YAML files plus ``--set key=value`` overrides.

Every failure is a :class:`~dobhil.errors.ConfigError` with one line naming the
key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from dobhil.config.schema import SECTIONS, Check, Config, check_maximum, key_fields
from dobhil.errors import ConfigError


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> Config:
    """Read ``path`` (YAML; None for the defaults), apply ``key=value`` overrides, validate."""
    flat = _flatten(read_yaml(path), "") if path is not None else {}
    for item in overrides:
        name, value = parse_override(item)
        flat[name] = value
    return build_config(flat, source=str(path) if path else "defaults")


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The mapping in a YAML file, or ConfigError naming the file (and line) at fault."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.__class__.__name__}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: YAML syntax error{_yaml_where(exc)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping of sections (plant:, design:, ...), "
                          f"got a {type(data).__name__}")
    return data


def _yaml_where(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or ""
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
    return f"{where}: {problem}" if problem else where


def _flatten(data: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in data.items():
        name = f"{prefix}{k}"
        if isinstance(v, Mapping) and prefix == "":
            out.update(_flatten(v, name + "."))
        else:
            out[name] = v
    return out


def parse_override(item: str) -> tuple[str, Any]:
    """``"design.force_gain=3"`` -> ``("design.force_gain", 3)`` (value parsed as YAML)."""
    name, sep, text = item.partition("=")
    if not sep or not name.strip():
        raise ConfigError(f"--set {item!r}: expected key=value, e.g. design.force_gain=3")
    try:
        value = yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError:
        value = text
    return name.strip(), value


def build_config(flat: Mapping[str, Any], *, source: str = "config") -> Config:
    """Validate a flat ``section.name -> value`` mapping into a frozen :class:`Config`."""
    fields = key_fields()
    values: dict[str, dict[str, Any]] = {s: {} for s in SECTIONS}
    for name, raw in flat.items():
        if name not in fields:
            raise ConfigError(_unknown_key(name, fields))
        section, attr = name.split(".")
        values[section][attr] = coerce(name, raw, fields[name])
    sections = {s: SECTIONS[s](**v) for s, v in values.items()}
    config = Config(**sections)
    check_consistency(config)
    return config


def _unknown_key(name: str, fields: Mapping[str, Any]) -> str:
    section = name.split(".")[0]
    if section not in SECTIONS:
        return (f"unknown config section {section!r} in key {name!r}; "
                f"allowed sections: {', '.join(SECTIONS)}")
    allowed = ", ".join(k.split(".")[1] for k in fields if k.startswith(section + "."))
    return f"unknown config key {name!r}; {section} allows: {allowed}"


def coerce(name: str, raw: Any, f: dataclasses.Field[Any]) -> Any:
    """Check one value's type and constraint; return it in the key's type."""
    kind = f.type if isinstance(f.type, type) else {"float": float, "int": int, "str": str,
                                                    "bool": bool}[str(f.type)]
    meta = f.metadata
    if kind is str:
        return _coerce_str(name, raw, meta["choices"])
    value = _coerce_number(name, raw, kind)
    _check_range(name, value, meta["check"])
    if (problem := check_maximum(name, value, meta)) is not None:
        raise ConfigError(problem)
    return value


def _coerce_str(name: str, raw: Any, choices: tuple[str, ...]) -> str:
    if not isinstance(raw, str):
        allowed = f"one of {', '.join(choices)}" if choices else "a string"
        raise ConfigError(f"{name} = {raw!r}: wrong type {type(raw).__name__}; allowed: {allowed}")
    if choices and raw not in choices:
        raise ConfigError(f"{name} = {raw!r}: not allowed; allowed: {', '.join(choices)}")
    return raw


def _coerce_number(name: str, raw: Any, kind: type) -> float | int:
    if isinstance(raw, int) and not isinstance(raw, bool) and abs(raw) > 2 ** 1023:
        raise ConfigError(f"{name} = {str(raw)[:20]}... ({len(str(raw))} digits): too large; "
                          "allowed: a finite number")
    if isinstance(raw, str):  # YAML 1.1 reads 1e-3 (no dot) as a string
        try:
            raw = float(raw)
        except ValueError:
            pass
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise ConfigError(f"{name} = {raw!r}: wrong type {type(raw).__name__}; "
                          f"allowed: {'an integer' if kind is int else 'a number'}")
    if kind is int:
        if float(raw) != int(raw):
            raise ConfigError(f"{name} = {raw!r}: must be a whole number")
        return int(raw)
    value = float(raw)
    if not math.isfinite(value):
        raise ConfigError(f"{name} = {raw!r}: must be a finite number")
    return value


def _check_range(name: str, value: float, check: Check) -> None:
    if check is Check.POSITIVE and not value > 0:
        raise ConfigError(f"{name} = {value!r}: must be > 0")
    if check is Check.NONNEGATIVE and not value >= 0:
        raise ConfigError(f"{name} = {value!r}: must be >= 0")


def check_consistency(config: Config) -> None:
    """Constraints between keys."""
    loop = config.loop
    if loop.position_min >= loop.position_max:
        raise ConfigError(f"loop.position_min = {loop.position_min!r} must be below "
                          f"loop.position_max = {loop.position_max!r}")
    if loop.feedback_timeout < loop.period:
        raise ConfigError(f"loop.feedback_timeout = {loop.feedback_timeout!r}: must be at least "
                          f"loop.period = {loop.period!r}")
    if config.reference.kind == "csv" and not config.reference.file:
        raise ConfigError("reference.kind = 'csv' needs reference.file (a CSV with time,tau_ref)")


def to_yaml(config: Config) -> str:
    """The resolved configuration as YAML (sections of keys)."""
    nested = {s: dataclasses.asdict(getattr(config, s)) for s in SECTIONS}
    return yaml.safe_dump(nested, sort_keys=False)
