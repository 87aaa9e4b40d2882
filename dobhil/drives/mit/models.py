"""The MIT model table, ``drivers/mit-models.yaml``: (vendor, model, firmware) -> :class:`MitModel`.

The shipped table is found as the shipped profiles are (``dobhil.data.drivers_dir()``: the
repository's ``drivers/`` or the installed ``dobhil.data.drivers``); a profile may name
another (``mit.models``). Every problem is one :class:`ConfigError` line naming the file,
the row and the key (``drivers/mit-models.yaml: models[3] (cubemars AK80-9): t_max: expected
a number > 0, got -1``). Tables are cached per file (path, size and modification time).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final


from dobhil.config.yamlio import load_yaml_file, show_value
from dobhil.drives.mit.codec import SPECIAL_NAMES, MitModel, ReplyLayout
from dobhil.errors import CodecError, ConfigError

__all__ = ["MODELS_FILE", "ModelKey", "find_model", "load_models", "shipped_models_path"]

#: the table's file name in ``drivers/``
MODELS_FILE: Final = "mit-models.yaml"

ModelKey = tuple[str, str, str]  # (vendor, model, firmware)

_TOP_KEYS: Final = ("reply_layouts", "models")
_LAYOUT_KEYS: Final = ("lengths", "id", "state", "extra", "errors", "states", "temperature",
                       "first_error_state", "source")
_RANGE_KEYS: Final = ("p_max", "v_max", "t_max", "kp_max", "kd_max")
_ROW_KEYS: Final = ("vendor", "model", "firmware", *_RANGE_KEYS, "reply", "position_at_limit",
                    "axis_direction", "command_timeout", "special", "source")
_OPTIONAL_ROW_KEYS: Final = ("note",)
#: the largest range the table accepts: beyond any actuator (a unit mistake)
_MAX_RANGE: Final = 1e5

_cache: dict[tuple[str, int, int], Mapping[ModelKey, MitModel]] = {}


def shipped_models_path() -> Path:
    """``mit-models.yaml`` among the shipped drive profiles."""
    from dobhil.data import drivers_dir
    return drivers_dir() / MODELS_FILE


def load_models(path: str | os.PathLike[str] | None = None) -> Mapping[ModelKey, MitModel]:
    """Every row of the table at ``path`` (default: the shipped one), validated, keyed by
    (vendor, model, firmware); read-only."""
    file = Path(path) if path is not None else shipped_models_path()
    try:
        stat = file.stat()
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise ConfigError(f"{file}: cannot read the MIT model table: {reason}") from None
    key = (str(file.resolve()), stat.st_size, stat.st_mtime_ns)
    cached = _cache.get(key)
    if cached is None:
        cached = _cache[key] = _parse(_read(file), str(file))
    return cached


def find_model(vendor: str, model: str, firmware: str,
               path: str | os.PathLike[str] | None = None) -> MitModel:
    """The row (vendor, model, firmware) of the table; missing -> one ConfigError line
    naming what the table has instead."""
    table = load_models(path)
    row = table.get((vendor, model, firmware))
    if row is not None:
        return row
    where_ = str(path) if path is not None else f"drivers/{MODELS_FILE}"
    firmwares = sorted(f for v, m, f in table if (v, m) == (vendor, model))
    if firmwares:
        known = f"{vendor} {model} has firmware {', '.join(repr(f) for f in firmwares)}"
    else:
        models = sorted({m for v, m, _ in table if v == vendor})
        known = (f"{vendor} models: {', '.join(models)}" if models
                 else f"vendors: {', '.join(sorted({v for v, _, _ in table}))}")
    raise ConfigError(f"mit.model: no row for {vendor} {model} firmware {firmware!r} in {where_}; known: {known}")


def _read(file: Path) -> Any:
    return load_yaml_file(file, "the MIT model table")


def _mapping(value: Any, what: str, allowed: tuple[str, ...]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{what}: expected a mapping of {', '.join(allowed)}, got {show_value(value)}")
    for k in value:
        if k not in allowed:
            raise ConfigError(f"{what}: unknown key {show_value(k)} (allowed: {', '.join(allowed)})")
    return value


def _parse(data: Any, source: str) -> Mapping[ModelKey, MitModel]:
    top = _mapping(data, source, _TOP_KEYS)
    for k in _TOP_KEYS:
        if k not in top:
            raise ConfigError(f"{source}: missing key {k!r}")
    raw_layouts = top["reply_layouts"]
    if not isinstance(raw_layouts, Mapping) or not raw_layouts:
        raise ConfigError(f"{source}: reply_layouts: expected a mapping of layout names, got {show_value(raw_layouts)}")
    layouts = {str(name): _layout(str(name), spec, f"{source}: reply_layouts.{name}")
               for name, spec in raw_layouts.items()}
    rows = top["models"]
    if not isinstance(rows, list) or not rows:
        raise ConfigError(f"{source}: models: expected a list of rows, got {show_value(rows)}")
    out: dict[ModelKey, MitModel] = {}
    for i, row in enumerate(rows):
        model = _row(row, layouts, f"{source}: models[{i}]")
        if model.key in out:
            raise ConfigError(f"{source}: models[{i}]: {model.name} is given twice")
        out[model.key] = model
    return MappingProxyType(out)


def _int_map(value: Any, what: str, values: type) -> dict[Any, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{what}: expected a mapping, got {show_value(value)}")
    out: dict[Any, Any] = {}
    for k, v in value.items():
        if values is int:  # name -> byte index
            if not isinstance(k, str) or not isinstance(v, int) or isinstance(v, bool):
                raise ConfigError(f"{what}: {show_value(k)}: expected a name -> byte index, got {show_value(v)}")
        elif not isinstance(k, int) or isinstance(k, bool) or not isinstance(v, str):  # code -> text
            raise ConfigError(f"{what}: {show_value(k)}: expected an integer code -> text, got {show_value(v)}")
        out[k] = v
    return out


def _layout(name: str, spec: Any, what: str) -> ReplyLayout:
    spec = _mapping(spec, what, _LAYOUT_KEYS)
    lengths = spec.get("lengths")
    if not isinstance(lengths, list) or not lengths or not all(type(n) is int for n in lengths):
        raise ConfigError(f"{what}.lengths: expected a list of reply lengths in bytes, got {show_value(lengths)}")
    temperature = spec.get("temperature", "")
    first = spec.get("first_error_state", 8)
    if not isinstance(temperature, str) or type(first) is not int:
        raise ConfigError(f"{what}: temperature must name an extra byte and first_error_state be an integer")
    try:
        return ReplyLayout(
            name=name, lengths=tuple(lengths), id_field=str(spec.get("id", "byte0")),
            state_field=str(spec.get("state", "")),
            extra=_int_map(spec.get("extra", {}), f"{what}.extra", int),
            errors=_int_map(spec.get("errors", {}), f"{what}.errors", str),
            states=_int_map(spec.get("states", {}), f"{what}.states", str),
            temperature=temperature, first_error_state=first)
    except CodecError as exc:
        raise ConfigError(f"{what}: {exc}") from None


def _number(row: Mapping[str, Any], key: str, what: str, *, low: float, high: float, open_low: bool) -> float:
    value = row[key]
    if isinstance(value, str):  # YAML 1.1 reads 1e-3 as a string; 1.2 as a number
        try:
            value = float(value)
        except ValueError:
            pass
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) \
        and (value > low if open_low else value >= low) and value <= high
    if not ok:
        bound = f"> {low:g}" if open_low else f">= {low:g}"
        raise ConfigError(f"{what}: {key}: expected a number {bound} and <= {high:g}, got {show_value(row[key])}")
    return float(value)


def _row(row: Any, layouts: Mapping[str, ReplyLayout], what: str) -> MitModel:
    if isinstance(row, Mapping):
        names = [row.get(k) for k in ("vendor", "model", "firmware")]
        if all(isinstance(n, str) and n for n in names):
            what = f"{what} ({names[0]} {names[1]} firmware {names[2]!r})"
    row = _mapping(row, what, (*_ROW_KEYS, *_OPTIONAL_ROW_KEYS))
    for k in _ROW_KEYS:
        if k not in row:
            raise ConfigError(f"{what}: missing key {k!r}")
    for k in ("vendor", "model", "firmware", "source"):
        if not isinstance(row[k], str) or not row[k].strip():
            hint = " (quote a version: \"2.0\")" if k == "firmware" else ""
            raise ConfigError(f"{what}: {k}: expected a non-empty string{hint}, got {show_value(row[k])}")
    ranges = {k: _number(row, k, what, low=0.0, high=_MAX_RANGE, open_low=True) for k in _RANGE_KEYS}
    reply = row["reply"]
    if reply not in layouts:
        raise ConfigError(f"{what}: reply: expected one of {', '.join(layouts)} (reply_layouts), "
                          f"got {show_value(reply)}")
    if row["position_at_limit"] not in ("wrap", "saturate"):
        raise ConfigError(f"{what}: position_at_limit: expected wrap or saturate, "
                          f"got {show_value(row['position_at_limit'])}")
    if row["axis_direction"] not in (1, -1) or isinstance(row["axis_direction"], bool):
        raise ConfigError(f"{what}: axis_direction: expected 1 or -1, got {show_value(row['axis_direction'])}")
    timeout = None if row["command_timeout"] is None else \
        _number(row, "command_timeout", what, low=0.0, high=60.0, open_low=True)
    special = row["special"]
    if not isinstance(special, list) or any(s not in SPECIAL_NAMES for s in special):
        raise ConfigError(f"{what}: special: expected a list of {', '.join(SPECIAL_NAMES)}, got {show_value(special)}")
    note = row.get("note", "")
    if not isinstance(note, str):
        raise ConfigError(f"{what}: note: expected a string, got {show_value(note)}")
    try:
        return MitModel(vendor=row["vendor"], model=row["model"], firmware=row["firmware"], **ranges,
                        layout=layouts[reply], position_at_limit=row["position_at_limit"],
                        axis_direction=row["axis_direction"], command_timeout=timeout,
                        special=frozenset(SPECIAL_NAMES[s] for s in special), source=" ".join(row["source"].split()),
                        note=" ".join(note.split()))
    except CodecError as exc:
        raise ConfigError(f"{what}: {exc}") from None
