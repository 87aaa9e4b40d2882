"""The emulated drives speak through their protocol's codec: no enum or frame id of their
own, so a codec fix reaches the drive and its emulator at once (an emulator that kept a
private copy would keep agreeing with itself while the drive moved on)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import dobhil.drives
from dobhil.drives.cia402 import codec as cia402_codec
from dobhil.drives.cia402 import emulator as cia402_emulator
from dobhil.drives.mit import codec as mit_codec
from dobhil.drives.mit import emulator as mit_emulator

EMULATORS = sorted(Path(dobhil.drives.__file__).parent.glob("*/emulator.py"))


@pytest.mark.parametrize("path", EMULATORS, ids=lambda p: p.parent.name)
def test_an_emulator_defines_no_enum(path: Path) -> None:
    tree = ast.parse(path.read_text())
    enums = [node.name for node in ast.walk(tree) if isinstance(node, ast.ClassDef)
             and any(isinstance(b, ast.Name) and b.id in {"IntEnum", "IntFlag", "Enum"} for b in node.bases)]
    assert enums == [], f"{path.parent.name}/emulator.py defines {enums}: use its codec's"


def test_the_cia402_emulator_takes_the_codecs_controlword_and_ids() -> None:
    assert {type(command) for _, command in cia402_emulator.TRANSITIONS} == {cia402_codec.Controlword}
    assert cia402_emulator.decode_command(0x0F) is cia402_codec.Controlword.ENABLE_OPERATION
    source = Path(cia402_emulator.__file__).read_text()
    assert "Cob.NMT" in source and "Cob.HEARTBEAT" in source and "0x700" not in source


def test_the_mit_emulator_takes_the_codecs_register_ids() -> None:
    assert mit_emulator.REGISTER_ID is mit_codec.REGISTER_ID
    assert mit_emulator.REGISTER_READ is mit_codec.REGISTER_READ
