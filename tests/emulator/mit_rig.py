"""Shared by the MIT emulator tests: model rows by name and a profile built in code
(the loop and emulator tests need no profile file, nor the MIT drive)."""

from __future__ import annotations

from typing import Any

from dobhil.drives.profile import DriveProfile

#: (vendor, model, firmware) rows of drivers/mit-models.yaml the tests use
AK80_9 = ("cubemars", "AK80-9", "2")
DAMIAO = ("damiao", "DM4310", "1")
MINI_CHEETAH = ("mini-cheetah", "mini-cheetah", "1")


def mit_profile(row: tuple[str, str, str], *, node_id: int = 1, **options: Any) -> DriveProfile:
    vendor, model, firmware = row
    return DriveProfile(protocol="mit", firmware=firmware, node_id=node_id, torque_limit=2.0,
                        velocity_limit=20.0, enable_timeout=0.5, command_delay_periods=1,
                        options={"vendor": vendor, "model": model, **options}, name=f"{model}-test")
