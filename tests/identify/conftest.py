"""Logs of short emulated runs (lockstep: reproducible), made once per session by the CLI."""

from __future__ import annotations

from pathlib import Path

import pytest

from dobhil.cli.main import main



def emulated_log(path: Path, *sets: str, duration: float = 0.5) -> Path:
    """``dobhil run demo --emulate --lockstep --log path`` with ``sets`` (``key=value``)."""
    args = ["run", "demo", "--emulate", "--lockstep", "--log", str(path), "--set", f"loop.duration={duration}"]
    for item in sets:
        args += ["--set", item]
    assert main(args) in (0, 1)   # 1: a safety stop (a free servo reaching its position limit)
    assert path.is_file()
    return path


@pytest.fixture(scope="session")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("identify-logs")
    chirp = ("reference.kind=chirp", "reference.start=0", "reference.frequency=1", "reference.frequency_end=30")
    return {
        # starts free at -0.005 rad, engages the environment at 0 and presses on it
        "contact": emulated_log(d / "contact.mcap"),
        # the environment out of reach: free motion only
        "free": emulated_log(d / "free.mcap", *chirp, "reference.amplitude=0.2", "environment.contact_position=50"),
        # in contact from the start, no force asked: nothing moves
        "still": emulated_log(d / "still.mcap", "reference.amplitude=0", "reference.offset=0",
                              "plant.initial_position=0"),
    }
