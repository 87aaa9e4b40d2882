"""Every enum of ``dobhil/`` prints its own name: no value has a second name (an alias
prints as the first one: ``Cob.EMCY`` printed ``SYNC``). A flag's named combination of
several bits (``ALL = A | B``) is the one alias Python's ``enum`` intends: iteration yields
the single bits, so the combination is only in ``__members__``, and it prints its own name."""

from __future__ import annotations

import enum
import importlib
import inspect
import pkgutil

import pytest

import dobhil


def dobhil_enums() -> list[type[enum.Enum]]:
    found: dict[str, type[enum.Enum]] = {}
    for info in pkgutil.walk_packages(dobhil.__path__, "dobhil."):
        if info.name == "dobhil.__main__":
            continue
        module = importlib.import_module(info.name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, enum.Enum) and cls.__module__ == info.name:
                found[f"{cls.__module__}.{cls.__qualname__}"] = cls
    return [found[name] for name in sorted(found)]


def aliases(cls: type[enum.Enum]) -> dict[str, str]:
    """Each alias of ``cls`` -> the name it prints as (a flag's multi-bit combinations aside)."""
    out = {}
    for name, member in cls.__members__.items():
        if member.name == name:
            continue
        if issubclass(cls, enum.Flag) and bin(int(member.value)).count("1") > 1:
            continue
        out[name] = str(member.name)
    return out


ENUMS = dobhil_enums()


def test_the_walk_finds_the_enums_of_every_layer() -> None:
    names = {e.__qualname__ for e in ENUMS}
    assert {"Cob", "CmdId", "CmdId05", "CmdId06", "Timing"} <= names


@pytest.mark.parametrize("cls", ENUMS, ids=lambda e: f"{e.__module__}.{e.__qualname__}")
def test_no_enum_has_an_alias(cls: type[enum.Enum]) -> None:
    assert aliases(cls) == {}


def test_the_check_finds_an_alias_and_passes_a_flag_combination() -> None:
    class Twice(enum.IntEnum):
        SYNC = 0x080
        EMCY = 0x080

    class Bits(enum.IntFlag):
        A = 1
        B = 2
        BOTH = 3

    class BitTwice(enum.IntFlag):
        A = 1
        FIRST = 1

    assert aliases(Twice) == {"EMCY": "SYNC"}
    assert aliases(Bits) == {}
    assert aliases(BitTwice) == {"FIRST": "A"}
