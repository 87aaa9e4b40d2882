"""Load and validate configurations: YAML files plus ``--set key=value`` overrides.

Every failure is a :class:`~dobhil.errors.ConfigError` with one line naming the
key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, NoReturn

import yaml

from dobhil.config.schema import SECTIONS, Check, Config, check_maximum, check_minimum, key_fields
from dobhil.config.yamlio import TextFileError, read_text_file, safe_load, show_value, where
from dobhil.data import configs_dir, shipped_configs, shipped_file
from dobhil.errors import ConfigError, exception_line


#: keys naming a file: relative in a config file, from that file's directory (the run
#: resolves them); relative in a ``--set`` override, from the working directory
CWD_PATH_KEYS = ("reference.file",)


def load_config(path: str | Path | None = None, overrides: Iterable[str] = (),
                set_files: Iterable[str | Path] = ()) -> Config:
    """Read ``path`` (a YAML file or a shipped config name, see :func:`resolve_config`; None
    for the defaults), apply the ``set_files`` (``--set-file``: YAML mappings of keys, e.g. an
    identified overlay) in order, then the ``key=value`` overrides (``--set`` wins), validate."""
    flat = _flatten(read_yaml(resolve_config(path)), "") if path is not None else {}
    for extra in set_files:
        flat.update(read_set_file(extra))
    for item in overrides:
        name, value = parse_override(item)
        if name in CWD_PATH_KEYS and isinstance(value, str) and value:
            value = os.path.abspath(value)  # a path typed on the command line: from the working directory
        flat[name] = value
    return build_config(flat, source=str(path) if path else "defaults")


def resolve_config(path: str | Path) -> Path:
    """The file of a config given as a path or as a shipped name (``demo``, ``paper/fig2c``).

    An existing file is always that file; otherwise a shipped config of that name; otherwise
    ConfigError listing the shipped names. A directory is no config: one named like a shipped
    config (``dobhil demo --out demo`` writes one) leaves the name to the shipped file.
    """
    if not str(path).strip():
        raise ConfigError(f"config {str(path)!r}: empty; expected a YAML file or a shipped config name: "
                          f"{', '.join(shipped_configs())}")
    p = Path(path)
    try:
        if p.exists() and not (p.is_dir() and shipped_file(configs_dir(), str(path)) is not None):
            return p
    except (OSError, ValueError) as exc:  # a name too long for the file system, a NUL byte
        raise ConfigError(f"config {_show(str(path))}: not a usable file name "
                          f"({getattr(exc, 'strerror', None) or exc})") from None
    found = shipped_file(configs_dir(), str(path))
    if found is not None:
        return found
    raise ConfigError(f"config {_show(str(path))}: no such file, and not a shipped config name; shipped: "
                      f"{', '.join(shipped_configs())} (dobhil init DIR copies them for editing)")


def read_yaml(path: str | Path, *, name: str | None = None, expected: str | None = None) -> dict[str, Any]:
    """The mapping in a YAML file, or ConfigError naming the file (and line) at fault.

    ``name`` is how the file is named in a message (``--set-file 'x.yaml'``: what the user
    typed, not a config file) and ``expected`` what it should hold; with them, every refusal
    is ``NAME: what is wrong; expected EXPECTED``."""
    p = Path(path)
    if name is not None:
        return _read_named_yaml(p, name, expected or "a YAML mapping")
    try:
        text = read_text_file(p)
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist") from None
    except TextFileError as exc:
        raise ConfigError(f"config file {p} {exc}") from None
    try:
        data = safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: YAML syntax error{where(exc)}") from None
    except (ValueError, RecursionError) as exc:  # e.g. an integer of more than 4300 digits
        raise ConfigError(f"{p}: unreadable value: {exception_line(exc, named=False)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping of sections (plant:, design:, ...), "
                          f"got a {type(data).__name__}")
    return data


def _read_named_yaml(p: Path, name: str, expected: str) -> dict[str, Any]:
    def refuse(problem: str) -> NoReturn:
        raise ConfigError(f"{name}: {problem}; expected {expected}")
    try:
        text = read_text_file(p)
    except FileNotFoundError:
        refuse("no such file")
    except TextFileError as exc:
        refuse(str(exc))  # a directory, a device, not UTF-8 text (an image), too large
    try:
        data = safe_load(text)
    except yaml.YAMLError as exc:
        refuse(f"YAML syntax error{where(exc)}")
    except (ValueError, RecursionError) as exc:  # e.g. an integer of more than 4300 digits
        refuse(f"unreadable value: {exception_line(exc, named=False)}")
    if data is None:
        return {}
    if not isinstance(data, dict):
        refuse(f"holds a YAML {_yaml_kind(data)}, not a mapping")
    return data


def _yaml_kind(data: Any) -> str:
    """What a YAML document that is no mapping holds, in YAML's words (a list, not a Python ``list``)."""
    if isinstance(data, list):
        return "list"
    if isinstance(data, str):
        return "string (plain text)"
    return "scalar" if isinstance(data, (bool, int, float)) else type(data).__name__


#: what a ``--set-file`` holds, as its refusals say
SET_FILE_EXPECTED = ("a YAML file of section.key: value (e.g. plant.inertia: 0.25, or the overlay "
                     "dobhil identify --out writes)")

#: the top-level key of an identify overlay that --set-file skips (the fit's intervals and covariance)
IDENTIFIED_SECTION = "identified"


def read_set_file(path: str | Path) -> dict[str, Any]:
    """The keys of a ``--set-file``: a YAML mapping of ``section.key: value`` (or of sections,
    as in a config file); unknown keys fail later, in :func:`build_config`, naming the key."""
    data = dict(read_yaml(path, name=f"--set-file {_show(str(path))}", expected=SET_FILE_EXPECTED))
    # an identify overlay's fit record (intervals, covariance: dobhil/identify/intervals.py) is no config key
    data.pop(IDENTIFIED_SECTION, None)
    flat = _flatten(data, "")
    for name, value in flat.items():
        if "." not in name or isinstance(value, Mapping):
            raise ConfigError(f"--set-file {_show(str(path))}: {_show(name)} is not a section.key with a "
                              "value (e.g. plant.inertia: 0.25)")
        if name in CWD_PATH_KEYS and isinstance(value, str) and value:
            flat[name] = os.path.join(os.path.dirname(os.path.abspath(path)), value)  # as in its own file
    return flat


def _flatten(data: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """``{section: {key: v}}`` (or ``{"section.key": v}``) as ``{"section.key": v}``; a key
    given both ways in one mapping is refused, as a key given twice in YAML is."""
    out: dict[str, Any] = {}
    for k, v in data.items():
        name = f"{prefix}{k}"
        inner = _flatten(v, name + ".") if isinstance(v, Mapping) and prefix == "" else {name: v}
        for key, value in inner.items():
            if key in out:
                raise ConfigError(f"{key}: given twice in one mapping (as a section's key and as "
                                  f"{key!r}); give it once")
            out[key] = value
    return out


def parse_override(item: str) -> tuple[str, Any]:
    """``"design.force_gain=3"`` -> ``("design.force_gain", 3)`` (value parsed as YAML)."""
    name, sep, text = item.partition("=")
    if not sep or not name.strip():
        raise ConfigError(f"--set {_show(item)}: expected key=value, e.g. design.force_gain=3")
    try:
        value = safe_load(text) if text.strip() else ""
    except (yaml.YAMLError, ValueError, RecursionError):
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
        return (f"unknown config section {_show(section)} in key {_show(name)}; "
                f"allowed sections: {', '.join(SECTIONS)}")
    allowed = ", ".join(k.split(".")[1] for k in fields if k.startswith(section + "."))
    if name == section:   # `--set loop=1`, or `loop: 5` in a file: a section, not a key
        return (f"{_show(name)} is a config section, not a key: give {section}.KEY (a mapping in "
                f"YAML); {section} allows: {allowed}")
    return f"unknown config key {_show(name)}; {section} allows: {allowed}"


def coerce(name: str, raw: Any, f: dataclasses.Field[Any]) -> Any:
    """Check one value's type and constraint; return it in the key's type."""
    kind = f.type if isinstance(f.type, type) else {"float": float, "int": int, "str": str,
                                                    "bool": bool}[str(f.type)]
    meta = f.metadata
    if kind is str:
        return _coerce_str(name, raw, meta["choices"])
    value = _coerce_number(name, raw, kind)
    _check_range(name, value, meta["check"])
    if (problem := check_maximum(name, value, meta) or check_minimum(name, value, meta)) is not None:
        raise ConfigError(problem)
    return value


def _show(raw: Any) -> str:
    """``repr(raw)``, short: a value quoted in a one-line error (see :func:`show_value`)."""
    return show_value(raw)


def _coerce_str(name: str, raw: Any, choices: tuple[str, ...]) -> str:
    if not isinstance(raw, str):
        allowed = f"one of {', '.join(choices)}" if choices else "a string"
        raise ConfigError(f"{name} = {_show(raw)}: wrong type {type(raw).__name__}; allowed: {allowed}")
    if choices and raw not in choices:
        raise ConfigError(f"{name} = {_show(raw)}: not allowed; allowed: {', '.join(choices)}")
    return raw


#: no key has a physical value beyond this magnitude (SI units); larger numbers are typos,
#: and would overflow the drive's float32 fields or the simulation
MAX_MAGNITUDE = 1e15
#: integer keys (counts, seeds, bit rates) fit a signed 64-bit integer
MAX_INT = 2**63 - 1


def _coerce_number(name: str, raw: Any, kind: type) -> float | int:
    if isinstance(raw, str):  # YAML 1.1 reads 1e-3 (no dot) as a string
        try:
            number = float(raw)
        except ValueError:
            pass
        else:
            return _coerce_number(name, number, kind) if math.isfinite(number) else _not_finite(name, raw)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise ConfigError(f"{name} = {_show(raw)}: wrong type {type(raw).__name__}; "
                          f"allowed: {'an integer' if kind is int else 'a number'}")
    if kind is int:
        return _coerce_int(name, raw)
    try:
        value = float(raw)
    except OverflowError:  # an integer beyond the float range
        value = math.inf
    else:
        if not math.isfinite(value):  # nan or inf from YAML (.nan, .inf)
            _not_finite(name, raw)
    if abs(value) > MAX_MAGNITUDE:
        raise ConfigError(f"{name} = {_show(raw)}: outside the physical range; allowed: "
                          f"|value| <= {MAX_MAGNITUDE:g} (SI units)")
    return value


def _not_finite(name: str, raw: Any) -> NoReturn:
    raise ConfigError(f"{name} = {_show(raw)}: must be a finite number")


def _coerce_int(name: str, raw: int | float) -> int:
    if isinstance(raw, float):
        if not math.isfinite(raw):
            _not_finite(name, raw)
        if raw != int(raw):
            raise ConfigError(f"{name} = {_show(raw)}: must be a whole number")
        raw = int(raw)
    if abs(raw) > MAX_INT:
        raise ConfigError(f"{name} = {_show(raw)}: too large; allowed: |value| <= 2**63 - 1")
    return raw


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
    drive = config.drive
    if drive.channel and not drive.interface:
        # resolve_bus (dobhil/runtime/buses.py) reads an empty interface as the profile's whole bus:
        # the channel given would be dropped and the error would name the profile's bus, not this one
        raise ConfigError(f"drive.channel = {_show(drive.channel)} with drive.interface = {_show(drive.interface)}: "
                          "a channel needs its interface (an empty drive.interface is the drive profile's own "
                          "bus); give drive.interface too (a python-can interface, e.g. socketcan or virtual) "
                          "or leave drive.channel empty")
    if config.reference.kind == "csv" and not config.reference.file:
        raise ConfigError("reference.kind = 'csv' needs reference.file (a CSV with time,tau_ref)")
    check_instability(config)
    ref = config.reference
    if ref.kind == "multisine" and ref.lines > 1 and not ref.frequency_end > ref.frequency:
        raise ConfigError(f"reference.frequency_end = {ref.frequency_end!r}: the multisine band must "
                          f"end above reference.frequency = {ref.frequency!r} (or reference.lines = 1)")


def check_instability(config: Config) -> None:
    """Growth means a factor above 1. (A window shorter than two loop periods is not refused:
    the default would refuse a long ``loop.period``; the runtime takes two periods then.)"""
    watch = config.instability
    if not watch.growth > 1.0:
        raise ConfigError(f"instability.growth = {watch.growth!r}: must be > 1 (a factor of growth)")


def to_yaml(config: Config) -> str:
    """The resolved configuration as YAML (sections of keys)."""
    nested = {s: dataclasses.asdict(getattr(config, s)) for s in SECTIONS}
    return yaml.safe_dump(nested, sort_keys=False)
