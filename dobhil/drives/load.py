"""Drive profiles read from files (or a log's metadata) and validated against the
protocols the registry knows (:mod:`dobhil.drives.registry`).

:mod:`dobhil.drives.profile` holds the one validator and takes the protocols' rules as an
argument (:class:`~dobhil.drives.profile.ProtocolLookup`): the drive classes import it, so it
cannot import the registry that imports them. This module imports both and passes the
registry's look-up, so callers never have to.

``load_profile(name_or_path)`` accepts a path to a YAML file, or a profile name looked
up as ``<name>.yaml`` in the nearest ``drivers/`` directory above ``near`` (the config's
directory: the layout of the repository and of ``dobhil init``), then among the shipped
profiles (``drivers/`` of the repository, installed as ``dobhil.data.drivers``; see
:mod:`dobhil.data`). Every key is documented in ``drivers/README.md``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from dobhil.config.schema import Config
from dobhil.config.yamlio import load_yaml_file, show_value
from dobhil.drives.profile import DriveProfile, default_drivers_dir
from dobhil.drives.profile import profile_from_mapping as validate_profile
from dobhil.drives.registry import PROFILE_LOOKUP
from dobhil.errors import ConfigError

__all__ = ["load_drive_profile", "load_profile", "profile_from_mapping"]


def profile_from_mapping(data: Mapping[str, Any], *, source: str = "<profile>",
                         directory: str = "") -> DriveProfile:
    """Validate a mapping against the registry's protocols and build a DriveProfile
    (:func:`dobhil.drives.profile.profile_from_mapping`); ConfigError names key, value and rule."""
    return validate_profile(data, protocols=PROFILE_LOOKUP, source=source, directory=directory)


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


def _resolve(name_or_path: str | os.PathLike[str], drivers_dir: Path | None, near: Path | None) -> Path:
    text = os.fspath(name_or_path)
    candidate = Path(text)
    if candidate.suffix in (".yaml", ".yml") or os.sep in text or "/" in text:
        if _exists(candidate):
            return candidate  # a directory, FIFO or device is refused, with its reason, when read
        raise ConfigError(f"profile file {show_value(text)} does not exist")
    found = _near(text, near) if near is not None and drivers_dir is None else None
    if found is not None:
        return found
    directory = drivers_dir if drivers_dir is not None else default_drivers_dir()
    path = directory / f"{text}.yaml"
    if _is_file(path):
        return path
    from dobhil.data import DRIVER_TABLES  # data tables beside the profiles are not profiles
    known = sorted(p.stem for p in directory.glob("*.yaml") if p.stem not in DRIVER_TABLES) \
        if directory.is_dir() else []
    hint = f"in {directory}" if drivers_dir is not None else \
        f"(shipped), or {text if len(text) <= 60 else 'NAME'}.yaml in a drivers/ directory above the config, " \
        "or a path to a .yaml file"
    raise ConfigError(f"drive profile {show_value(text)}: expected one of {known} {hint}")


def load_profile(
    name_or_path: str | os.PathLike[str], *, drivers_dir: Path | None = None, near: Path | None = None,
    node_id: int | None = None,
) -> DriveProfile:
    """Load a profile by name (from ``drivers_dir``, else a ``drivers/`` above ``near``, else the
    shipped ones) or an explicit YAML path into a DriveProfile. ``node_id`` (a config's
    ``drive.node_id``) replaces the file's before validation, so the protocol's own rule for
    node ids checks it (an ODrive's 6 bits, a CANopen node's 1-127)."""
    path = _resolve(name_or_path, drivers_dir, near)
    data = load_yaml_file(path, "drive profile")
    data = {"name": path.stem, **(data or {})} if isinstance(data, Mapping) else data
    source = str(path)
    if node_id is not None and isinstance(data, Mapping):
        data = {**data, "node_id": node_id}
        source = f"{path} with drive.node_id = {node_id}"
    return profile_from_mapping(data, source=source, directory=str(path.resolve().parent))


def drive_profile_file(name: str, base_dir: Path) -> Path:
    """The file :func:`load_drive_profile` reads for ``drive.profile = name`` in a config of
    ``base_dir``: a YAML path from that directory, else the name looked up near it, else the
    shipped profile; ConfigError when there is none."""
    found = _yaml_path(name, base_dir)
    return found if found is not None else _resolve(name, None, base_dir)


def _yaml_path(name: str, base_dir: Path | None) -> Path | None:
    """``name`` as an existing YAML file, relative to ``base_dir`` unless absolute; None when
    it is none (then a profile name, looked up by :func:`_resolve`)."""
    candidate = base_dir / name if base_dir and not Path(name).is_absolute() else Path(name)
    return candidate if candidate.suffix in (".yaml", ".yml") and _exists(candidate) else None


def load_drive_profile(config: Config, base_dir: Path | None = None) -> DriveProfile:
    """The profile ``drive.profile`` of ``config`` names: a YAML file relative to ``base_dir``
    (the config's directory) if there is one, else a profile name looked up near it; its node
    id replaced by ``drive.node_id`` unless that is -1."""
    name = config.drive.profile
    found = _yaml_path(name, base_dir)
    node_id = config.drive.node_id if config.drive.node_id >= 0 else None
    return load_profile(str(found) if found is not None else name, near=base_dir, node_id=node_id)
