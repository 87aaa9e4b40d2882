"""Package layout that pyproject.toml alone cannot say: ``configs/`` and ``drivers/`` stay
at the top of the repository and ship inside the package as ``dobhil.data.configs`` and
``dobhil.data.drivers`` (read with importlib.resources, see dobhil/data/__init__.py).
Every other setting is in pyproject.toml."""

from pathlib import Path

from setuptools import find_namespace_packages, setup

ROOT = Path(__file__).resolve().parent
#: package -> top-level directory it is built from
DATA = {"dobhil.data.configs": "configs", "dobhil.data.drivers": "drivers"}


def data_packages() -> dict[str, str]:
    """Each data directory and its subdirectories as a package -> directory mapping."""
    out: dict[str, str] = {}
    for package, top in DATA.items():
        for d in [ROOT / top, *sorted(p for p in (ROOT / top).rglob("*") if p.is_dir())]:
            rel = d.relative_to(ROOT / top)
            if d.name == "__pycache__" or any(part.startswith(".") for part in rel.parts):
                continue
            out[".".join((package, *rel.parts))] = d.relative_to(ROOT).as_posix()
    return out


MAPPED = data_packages()

setup(
    # namespace discovery, as pyproject's `find` does: some subpackages have no __init__.py
    packages=find_namespace_packages(include=["dobhil", "dobhil.*"], exclude=["*.__pycache__"]) + list(MAPPED),
    package_dir={pkg: path for pkg, path in MAPPED.items() if pkg in DATA},
    package_data={"dobhil": ["py.typed"], **{pkg: ["*"] for pkg in MAPPED}},
    exclude_package_data={"": ["*.pyc", "__pycache__"]},
)
