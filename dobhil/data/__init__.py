"""The files dobhil ships: run and design configs, and drive profiles.

In the repository they stay at the top, ``configs/`` and ``drivers/``, where users
look for them; the build maps those two directories into this package as
``dobhil.data.configs`` and ``dobhil.data.drivers`` (``setup.py``), so a wheel and an
editable install both find them through :mod:`importlib.resources`, from any
directory. Only a bare source tree that was never installed (``sys.path`` pointing at
the checkout) falls back to the directories beside the package.

Names are paths relative to those directories without the ``.yaml`` suffix:
``demo``, ``paper/fig2c``, ``odrive-0.6``.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from dobhil.errors import DobhilError

__all__ = ["CONFIGS", "DRIVERS", "DRIVER_TABLES", "configs_dir", "copy_shipped", "drivers_dir", "shipped_configs",
           "shipped_file", "shipped_profiles"]

#: package of the shipped configs (``configs/`` in the repository)
CONFIGS = "dobhil.data.configs"
#: package of the shipped drive profiles (``drivers/`` in the repository)
DRIVERS = "dobhil.data.drivers"
_SOURCE_DIRS = {CONFIGS: "configs", DRIVERS: "drivers"}
_SUFFIXES = (".yaml", ".yml")
#: YAML files among the drive profiles that are data tables, not profiles (the MIT
#: model table, ``dobhil.drives.mit.models``): shipped and copied by ``init``, never
#: listed as a profile
DRIVER_TABLES = frozenset({"mit-models"})


def _package_dir(package: str) -> Path:
    try:
        root = importlib.resources.files(package)
    except ModuleNotFoundError:  # a source tree on sys.path, never installed
        return Path(__file__).resolve().parents[2] / _SOURCE_DIRS[package]
    if not isinstance(root, Path):
        raise DobhilError(f"{package} is not a directory on disk ({type(root).__name__}); "
                          "install dobhil unzipped (pip does) to use its shipped files")
    return root


def configs_dir() -> Path:
    """The directory of the shipped configs."""
    return _package_dir(CONFIGS)


def drivers_dir() -> Path:
    """The directory of the shipped drive profiles."""
    return _package_dir(DRIVERS)


def _names(directory: Path) -> list[str]:
    if not directory.is_dir():
        return []
    files = (p for p in directory.rglob("*") if p.suffix in _SUFFIXES and p.is_file())
    return sorted(p.relative_to(directory).with_suffix("").as_posix() for p in files
                  if not any(part.startswith(("_", ".")) for part in p.relative_to(directory).parts))


def shipped_configs() -> list[str]:
    """Names of the shipped configs, e.g. ``["demo", "paper/fig2a", ...]``."""
    return _names(configs_dir())


def shipped_profiles() -> list[str]:
    """Names of the shipped drive profiles, e.g. ``["odrive-0.5", "odrive-0.6"]`` (not the
    data tables beside them, :data:`DRIVER_TABLES`)."""
    return [name for name in _names(drivers_dir()) if name not in DRIVER_TABLES]


def shipped_file(directory: Path, name: str) -> Path | None:
    """``directory/<name>.yaml`` (or ``.yml``, or ``name`` itself with a suffix) if shipped there."""
    name = name.replace("\\", "/").strip("/")
    if not name or ".." in name.split("/"):
        return None
    stems = [name] if name.endswith(_SUFFIXES) else [name + s for s in _SUFFIXES]
    for stem in stems:
        path = directory / stem
        try:
            if path.is_file():
                return path
        except (OSError, ValueError):  # a name too long for the file system: not shipped
            return None
    return None


def _shipped_files(directory: Path) -> list[Path]:
    """Every file a user may edit under ``directory`` (not the package's ``__init__.py``, caches)."""
    return sorted(p for p in directory.rglob("*") if p.is_file()
                  and not any(part.startswith(("_", ".")) for part in p.relative_to(directory).parts))


def copy_shipped(dest: Path) -> list[Path]:
    """Copy the shipped configs and drive profiles to ``dest/configs`` and ``dest/drivers``.

    Never overwrites: when any target exists nothing is written and DobhilError names it.
    On any failure the files written so far are removed. Returns the files written.
    """
    if not str(dest).strip():
        raise DobhilError("target directory '': empty; give a directory, e.g. dobhil init my-project")
    try:
        if dest.exists() and not dest.is_dir():
            raise DobhilError(f"{dest} exists and is not a directory")
        plan = [(src, dest / top / src.relative_to(root))
                for top, root in (("configs", configs_dir()), ("drivers", drivers_dir()))
                for src in _shipped_files(root)]
        blocked = [d for d in {dst.parent for _, dst in plan} | {dest} if d.exists() and not d.is_dir()]
        clash = [dst for _, dst in plan if dst.exists() or dst.is_symlink()]
    except OSError as exc:  # a name the file system refuses (too long, a loop of links)
        raise DobhilError(f"cannot write {dest}: {exc.strerror or exc}") from None
    if blocked:
        raise DobhilError(f"{min(blocked)} exists and is not a directory; init never overwrites: "
                          "remove it or choose another directory")
    if clash:
        raise DobhilError(f"{clash[0]} exists ({len(clash)} of {len(plan)} files would be overwritten); "
                          "init never overwrites: remove them or choose another directory")
    written: list[Path] = []
    made: list[Path] = []  # directories this call created, removed again on failure
    try:
        for src, dst in plan:
            missing = [d for d in (dst.parent, *dst.parent.parents) if not d.exists()]
            dst.parent.mkdir(parents=True, exist_ok=True)
            made.extend(reversed(missing))
            with dst.open("xb") as fh:  # exclusive: a file that appeared meanwhile is not overwritten
                written.append(dst)
                fh.write(src.read_bytes())
    except OSError as exc:
        for path in written:
            path.unlink(missing_ok=True)
        for directory in reversed(made):
            try:
                directory.rmdir()  # only if empty: never removes what was there before
            except OSError:
                pass
        raise DobhilError(f"cannot write {dest}: {exc.strerror or exc}") from None
    return written
