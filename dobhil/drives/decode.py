"""A recorded run's drive, offline: its profile from the log's ``drive`` metadata and its
motion frames decoded by the drive class of that profile (``Drive.apply``), so a replay or an
identification counts and scales feedback exactly as the run did. Nothing is ever sent.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping

import can

from dobhil.drives.load import profile_from_mapping

from dobhil.drives.profile import RENAMED_KEYS, DriveProfile
from dobhil.errors import ConfigError, LogFileError


def recorded_profile(record: Mapping[str, str] | None, source: str) -> DriveProfile:
    """The profile of a log's ``drive`` metadata (values JSON). A recorded profile is read
    under today's key names: a user's YAML with an old name is refused, but a log written
    before the rename is not the user's to edit."""
    if not record:
        raise LogFileError(f"{source}: no 'drive' metadata (not a recorded run?)")
    try:
        values = {RENAMED_KEYS.get(k, k): json.loads(v) for k, v in record.items()}
        return profile_from_mapping(values, source=f"{source} drive")
    except (ValueError, ConfigError) as exc:
        raise LogFileError(f"{source}: invalid recorded drive profile: {exc}") from None


class _NoBus:
    """Stands in for the bus of the decoding drive: decoding never sends."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise LogFileError("an offline decoding drive cannot send")

    def recv(self, timeout: float | None = None) -> None:
        return None


def decode_motion(profile: DriveProfile, frames: Iterable[can.Message]) -> list[tuple[float, float, float]]:
    """``(frame timestamp, position, velocity)`` of every motion frame among ``frames``
    (the frames in bus order; any other frame, a command included, is skipped), decoded by the
    profile's own drive class; the i-th entry is
    the feedback of ``seq`` i + 1."""
    from dobhil.drives.registry import make_drive
    drive = make_drive(_NoBus(), profile, clock=lambda: 0.0)  # type: ignore[arg-type]
    out: list[tuple[float, float, float]] = []
    for msg in frames:
        if drive.apply(msg) and drive.feedback is not None:
            out.append((float(msg.timestamp), drive.feedback.position, drive.feedback.velocity))
    return out


__all__ = ["decode_motion", "recorded_profile"]
