"""The delay a drive's protocol imposes on each command, where the design meets the drive.

Most drives apply a torque command when it arrives: the delay between the feedback
sample and the torque reaching the motor is the host's compute and the bus, which the
config states (``design.delay_samples`` whole periods + ``design.input_delay``). Some
protocols fix that delay themselves: a CiA 402 drive latches a synchronous RPDO and
applies it at the next SYNC, exactly one loop period after the sample its TPDO carried,
however fast the host answered. Such a profile says so (``command_delay_periods``), and
then the design must be analysed, synthesised and emulated with that delay and no
other: :func:`effective_config` is the one place that turns the profile's promise into
the config every consumer uses -- the run's controller and its lockstep emulator,
``dobhil analyze`` and ``dobhil sweep``, ``dobhil replay`` and the run report's
prediction.
"""

from __future__ import annotations

import dataclasses

from dobhil.config.schema import Config
from dobhil.drives.profile import DriveProfile

__all__ = ["effective_config", "with_command_delay"]


def with_command_delay(config: Config, periods: int | None, source: str = "the drive profile") -> tuple[Config, str]:
    """``config`` with ``design.delay_samples = periods`` and ``design.input_delay = 0``
    when ``periods`` is set (the protocol's latch makes the delay, nothing fractional
    remains), and a one-line note when that changed the config's values ("" otherwise)."""
    if periods is None:
        return config, ""
    design = config.design
    if design.delay_samples == periods and design.input_delay == 0.0:
        return config, ""
    note = (f"{source}: command_delay_periods = {periods} (the protocol applies each command "
            f"{periods} loop period{'' if periods == 1 else 's'} after its sample): using "
            f"design.delay_samples = {periods}, design.input_delay = 0 instead of the config's "
            f"{design.delay_samples}, {design.input_delay:g}")
    new = dataclasses.replace(design, delay_samples=periods, input_delay=0.0)
    return dataclasses.replace(config, design=new), note


def effective_config(config: Config, profile: DriveProfile) -> tuple[Config, str]:
    """The config the design is analysed, synthesised and emulated with on this drive:
    its protocol's command delay (``profile.command_delay_periods``) replaces the
    config's when the profile sets one; plus the note saying so ("" when nothing changed)."""
    return with_command_delay(config, profile.command_delay_periods,
                              f"drive profile {profile.name or profile.protocol!r}")
