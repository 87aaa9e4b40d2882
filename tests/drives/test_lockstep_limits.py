"""What each protocol tells a lockstep run before any bus opens: the frames its drive sends
by itself at a fixed period (``DriveProtocol.periodic_sends``: a CiA 402 SYNC, the host's
heartbeat), which the lockstep bus sends only every whole number of loop periods, and
whether its feedback streams (``DriveProtocol.feedback_streams``: a single-axis lockstep
run takes one cycle per frame). Every shipped profile's answer, the drive's own on a
lockstep bus, and the generic rules' edges (``dobhil.runtime.session.check_lockstep``,
``check_lockstep_feedback``)."""

from __future__ import annotations

import pytest

from dobhil.config import load_config
from dobhil.drives.emulated import lockstep_steps
from dobhil.drives.load import load_profile
from dobhil.drives.registry import protocol
from dobhil.errors import ConfigError
from dobhil.runtime.session import RunSession, check_lockstep, check_lockstep_feedback

#: shipped profile -> its periodic sends (what, period [s], key)
SENDS = {
    "epos4": [("SYNC", 0.001, "feedback_period"), ("host heartbeat", 0.025, "cia402.consumer_heartbeat")],
    "cia402-emulated": [("SYNC", 0.001, "feedback_period")],   # consumer off: no host heartbeat
    "odrive-0.6": [], "moteus-r4.11": [], "mini-cheetah": [], "dm4310": [],
}


@pytest.mark.parametrize("name", SENDS)
def test_each_shipped_profile_lists_its_periodic_frames(name: str) -> None:
    profile = load_profile(name)
    sends = protocol(profile.protocol).periodic_sends(profile)
    assert [(s.what, pytest.approx(s.period), s.key) for s in sends] == SENDS[name]
    for s in sends:   # every one fits the lockstep bus at loop.period = feedback_period, none at twice it
        assert lockstep_steps(s.period, 0.001) >= 1 and not lockstep_steps(s.period, 0.002)
    check_lockstep(profile, 0.001)


@pytest.mark.parametrize("name", ["epos4", "cia402-emulated"])
@pytest.mark.parametrize("period", [0.0015, 0.002, 0.003, 0.03])
def test_a_period_the_sync_is_no_whole_number_of_is_refused(name: str, period: float) -> None:
    with pytest.raises(ConfigError, match=r"sends SYNC every 0.001 s \(feedback_period\); allowed in lockstep: "
                                          r"loop.period = 0.001 s \(feedback_period\), or a run in real time$"):
        check_lockstep(load_profile(name), period)


@pytest.mark.parametrize("name", ["odrive-0.6", "cia402-emulated", "mini-cheetah", "moteus-r4.11"])
def test_the_protocol_says_what_its_drive_does_on_a_lockstep_bus(name: str) -> None:
    """``feedback_streams`` before a bus opens is the drive's own on the lockstep bus."""
    with RunSession(load_config("demo", [f"drive.profile={name}"]), emulate=True, lockstep=True) as session:
        assert protocol(session.profile.protocol).feedback_streams is session.drive.feedback_streams


def test_a_streaming_drive_runs_lockstep_only_at_its_feedback_period() -> None:
    odrive, mit = load_profile("odrive-0.6"), load_profile("mini-cheetah")
    check_lockstep_feedback(odrive, 0.001 * (1 + 1e-12))   # float sums: equal
    with pytest.raises(ConfigError, match="one cycle per feedback frame"):
        check_lockstep_feedback(odrive, 0.002)
    check_lockstep_feedback(mit, 0.002)   # one reply per command: any period
