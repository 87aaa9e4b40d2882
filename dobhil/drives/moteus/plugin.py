"""The moteus protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``moteus`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

import math

from dobhil.drives.moteus.codec import SCALINGS, Quantity, Resolution, arbitration_id
from dobhil.drives.moteus.drive import MoteusDrive
from dobhil.drives.moteus.states import fault_text, mode_text
from dobhil.drives.moteus.emulator import EmulatedMoteus
from dobhil.drives.moteus.rules import resolution
from dobhil.drives.plugin import CodecQuantisation, DriveProtocol, FrameIds
from dobhil.drives.profile import DriveProfile

__all__ = ["MoteusProtocol"]

_TAU = 2.0 * math.pi


class MoteusProtocol(DriveProtocol):
    name = "moteus"
    title = "moteus (mjbots) over CAN FD"
    fd = True
    feedback_streams = False   # one reply per command

    @property
    def drive_class(self) -> type[MoteusDrive]:
        return MoteusDrive

    @property
    def emulator_class(self) -> type[EmulatedMoteus]:
        return EmulatedMoteus

    def state_name(self, profile: DriveProfile, code: int) -> str:
        # a mode is 0 or more; below it the code is none of the controller's (a log with no
        # state recorded yet): the number, which the log's reader names "not reported"
        return mode_text(code) if code >= 0 else str(code)

    def error_text(self, profile: DriveProfile, code: int) -> str:
        return fault_text(code)

    def frame_ids(self, profile: DriveProfile) -> FrameIds:
        """The command to the node and its reply to the host (``destination | source << 8 |
        reply-requested << 15 | prefix << 16``, mjbots' reference manual, "CAN-FD
        communication"): both the node's own."""
        source, prefix = int(profile.options.get("source_id", 0)), int(profile.options.get("can_prefix", 0))
        node = profile.node_id
        return FrameIds(frozenset({arbitration_id(source, node, reply=True, prefix=prefix),
                                   arbitration_id(node, source, reply=False, prefix=prefix)}))

    def quantisation(self, profile: DriveProfile) -> CodecQuantisation | None:
        """One code of each chosen integer resolution in SI units (float: 0, no step); the
        firmware and the library convert by truncation toward zero (``ScaleSaturate`` in
        ``fw/moteus_controller.cc``, ``saturate`` in ``moteus/multiplex.py``), which for a
        non-negative value is the floor the model's ``truncates`` describes. None when all
        three are float."""
        chosen = {name: resolution(profile, f"{name}_resolution") for name in ("position", "velocity")}
        chosen["torque"] = resolution(profile, "command_resolution")
        if all(res is Resolution.F32 for res in chosen.values()):
            return None
        steps = {"position": SCALINGS[Quantity.POSITION].step(chosen["position"]) * _TAU,
                 "velocity": SCALINGS[Quantity.VELOCITY].step(chosen["velocity"]) * _TAU,
                 "torque": SCALINGS[Quantity.TORQUE].step(chosen["torque"])}
        return CodecQuantisation(position=steps["position"], velocity=steps["velocity"], torque=steps["torque"],
                                 truncates=True,
                                 source={f"{k}_resolution": chosen[k].name.lower() for k in chosen})
