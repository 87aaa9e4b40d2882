"""Config names for the ``dobhil`` python-can interface: ``demo`` or a YAML path.

:func:`config_path` is the one function that turns a ``channel`` into a config file.
The shipped configs are found next to the package (``configs/`` at the top of the
repository, which an editable install sees); when dobhil resolves shipped config names
itself (installed wheels carry them as package data), this module should call that.
"""

from __future__ import annotations

from pathlib import Path

import dobhil
from dobhil.errors import ConfigError

_SUFFIXES = (".yaml", ".yml")


def configs_dir() -> Path:
    """Where the shipped configs are."""
    return Path(dobhil.__file__).resolve().parent.parent / "configs"


def shipped_configs() -> tuple[str, ...]:
    """Names of the shipped configs (``demo``, ``paper/fig2c``, ...), sorted."""
    root = configs_dir()
    if not root.is_dir():
        return ()
    return tuple(sorted(p.relative_to(root).with_suffix("").as_posix()
                        for p in root.rglob("*") if p.suffix in _SUFFIXES and p.is_file()))


def config_path(name: str) -> Path:
    """The config file of a shipped config name or of a YAML path; ConfigError if neither."""
    path = Path(name)
    if path.suffix in _SUFFIXES:
        if path.is_file():
            return path
        raise ConfigError(f"config file {name} does not exist")
    shipped = configs_dir() / f"{name}.yaml"
    if name and ".." not in path.parts and shipped.is_file():
        return shipped
    names = ", ".join(shipped_configs()) or "none found"
    raise ConfigError(f"no config {name!r}: give a shipped config name ({names}) or a .yaml path")


__all__ = ["config_path", "configs_dir", "shipped_configs"]
