"""Reading IdentData from a dobhil log, finding its segments, and the one-line refusals."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.errors import ConfigError, LogFileError
from dobhil.identify.data import (
    CONTACT, FREE, MIN_SEGMENT, IdentData, Segment, check_motion, contact_mask, find_segments, parse_segment,
    read_log, segments_of,
)
from dobhil.recording.reader import open_log


def _truth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true position, feedback position, /controller u_sat) by cycle, read independently."""
    q, pos, u = {}, {}, {}
    with open_log(path) as log:
        for topic, _, p in log.iter_messages(["/emulator/truth", "/drive/feedback", "/controller"]):
            if topic == "/controller":
                u[p["cycle"]] = p["u_sat"]
            elif topic == "/drive/feedback" and p["cycle"] >= 0:
                pos[p["cycle"]] = p["position"]
    with open_log(path) as log:  # truth has no cycle field: in cycle order
        q = dict(enumerate(p["q"] for _, _, p in log.iter_messages(["/emulator/truth"])))
    n = len(u)
    return (np.array([q[k] for k in range(n)]), np.array([pos[k] for k in range(n)]),
            np.array([u[k] for k in range(n)]))


def test_reads_the_loop_records(logs: dict[str, Path]) -> None:
    data = read_log(logs["contact"])
    _, pos, u = _truth(logs["contact"])
    assert data.period == 1e-3 and data.protocol == "odrive" and data.source == "contact.mcap"
    assert data.samples == pos.size
    np.testing.assert_array_equal(data.t, np.arange(data.samples) * 1e-3)
    np.testing.assert_array_equal(data.position, pos)
    np.testing.assert_array_equal(data.torque, u)
    assert data.recorded["plant.inertia"] == 0.25 and data.recorded["environment.stiffness"] == 1e4
    assert "loop.period" not in data.recorded


def test_contact_found_where_the_emulator_was_in_contact(logs: dict[str, Path]) -> None:
    data = read_log(logs["contact"])
    truth = _truth(logs["contact"])[0] >= 0.0   # environment.contact_position = 0
    found = contact_mask(data)
    assert truth.any() and (~truth).any()
    assert np.mean(found == truth) > 0.9   # samples at the contact position itself may go either way
    first = int(np.flatnonzero(truth)[0])
    segments = find_segments(data)
    assert [s.kind for s in segments] == [FREE, CONTACT]
    assert abs(segments[1].start - first) <= 2 and segments[1].stop == data.samples


def test_free_motion_has_no_contact(logs: dict[str, Path]) -> None:
    data = read_log(logs["free"])
    assert find_segments(data) == (Segment(0, data.samples, FREE),)


def test_segments_of_literal_masks() -> None:
    assert MIN_SEGMENT == 25   # the literal masks below are laid out for it
    m = np.zeros(200, dtype=bool)
    m[40:] = True
    assert segments_of(m) == (Segment(0, 40, FREE), Segment(40, 200, CONTACT))
    m[80:83] = False   # a 3-sample bounce joins the contact
    assert segments_of(m) == (Segment(0, 40, FREE), Segment(40, 200, CONTACT))
    m[:5] = True       # a short first run joins the next
    assert segments_of(m)[0] == Segment(0, 40, FREE)
    m[100:150] = False  # left the contact for a while and came back: one contact experiment
    assert segments_of(m) == (Segment(0, 40, FREE), Segment(40, 200, CONTACT))
    m[100:] = False     # ... or left it for good
    assert segments_of(m) == (Segment(0, 40, FREE), Segment(40, 100, CONTACT), Segment(100, 200, FREE))


def test_found_segments_are_long_enough_for_the_fit() -> None:
    from dobhil.identify import fit
    assert MIN_SEGMENT > 2 * fit._SMOOTH + 2   # identify refuses shorter segments


def test_parse_segment(logs: dict[str, Path]) -> None:
    data = read_log(logs["contact"])
    assert parse_segment("0.2:0.45", data) == Segment(200, 450, CONTACT)
    assert parse_segment("0.0:0.1:free", data) == Segment(0, 100, FREE)
    for bad in ("0.2:0.9", "-1:0.2", "0.3:0.2", "a:b", "0.1", "0.1:0.2:wall", "0.1:0.105"):
        with pytest.raises(ConfigError, match="--segment"):
            parse_segment(bad, data)


def test_no_motion_refused(logs: dict[str, Path]) -> None:
    with pytest.raises(ConfigError, match="no motion|torque never changes"):
        read_log(logs["still"])
    flat = np.zeros(50)
    with pytest.raises(ConfigError, match="torque never changes"):
        check_motion(IdentData(1e-3, np.arange(50) * 1e-3, flat, np.linspace(0, 1, 50), flat, "", "odrive", {}))


def test_another_protocol_refused(logs: dict[str, Path]) -> None:
    with pytest.raises(ConfigError, match="'odrive' drive, but the profile given is 'mit'"):
        read_log(logs["contact"], protocol="mit")


def test_damaged_and_frames_only_logs_refused(logs: dict[str, Path], tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    shutil.copy(logs["contact"], cut)
    with open(cut, "r+b") as f:
        f.truncate(cut.stat().st_size // 2)
    with pytest.raises(LogFileError):
        read_log(cut)
    assert MIN_SEGMENT > 0


@pytest.fixture(scope="module")
def imported(logs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The contact run's frames exported to candump and imported back: frames only."""
    from dobhil.cli.main import main
    d = tmp_path_factory.mktemp("imported")
    assert main(["log", "export", str(logs["contact"]), "--can", "--format", "candump", "-o", str(d / "c.log")]) == 0
    assert main(["log", "import", str(d / "c.log"), "-o", str(d / "c.mcap")]) == 0
    return d / "c.mcap"


def test_imported_can_log_decodes_like_the_loop_records(logs: dict[str, Path], imported: Path) -> None:
    from dobhil.drives.load import load_profile
    loop = read_log(logs["contact"])
    frames = read_log(imported, profile=load_profile("odrive-0.6"), period=1e-3)
    assert frames.protocol == "odrive" and frames.recorded == {} and frames.period == 1e-3
    # motion frame 0 is the feedback controller.initialize used (cycle -1): cycle k is frame k + 1
    n = loop.samples
    np.testing.assert_array_equal(frames.position[1:n + 1], loop.position)
    np.testing.assert_array_equal(frames.velocity[1:n + 1], loop.velocity)
    # the torque as the drive decodes its float32 field; the last cycle's interval also holds the
    # safe stop's zero torque, which is what the plant had when the next motion frame came
    np.testing.assert_allclose(frames.torque[1:n], loop.torque[:-1], rtol=0, atol=1e-6)
    assert frames.torque[n] == 0.0 != loop.torque[-1]
    assert frames.torque[0] == 0.0   # before the first command
    default = read_log(imported, profile=load_profile("odrive-0.6"))
    assert default.period == pytest.approx(1e-3, rel=0.05)   # the period the frames' stamps show


def test_a_coded_torque_is_read_as_the_drive_applies_it(tmp_path: Path) -> None:
    """An MIT drive gets the torque as a 12-bit code and truncates it (8.8 mN m a code on an
    AK80-9): the torque a log's samples carry is the one the emulated plant received one
    period later (the drive applies each command on arrival, its reply is the next cycle's
    feedback), not the command u_sat -- fitted to that, a free run's inertia came out 10 % low."""
    from dobhil.cli.main import main
    path = tmp_path / "mit.mcap"
    sets = ("loop.duration=0.05", "loop.mode=torque", "reference.kind=chirp", "reference.start=0",
            "reference.frequency=5", "reference.frequency_end=50", "reference.amplitude=0.3")
    assert main(["run", "mit-demo", "--emulate", "--lockstep", "--log", str(path),
                 *(a for item in sets for a in ("--set", item))]) == 0
    data = read_log(path)
    with open_log(path) as log:
        applied = np.array([p["tau_motor"] for _, _, p in log.iter_messages(["/emulator/truth"])])
        sent = np.array([p["u_sat"] for _, _, p in log.iter_messages(["/controller"])])
    assert np.abs(sent[:-1] - applied[1:]).max() > 1e-3   # the code is a step coarser than the command
    np.testing.assert_allclose(data.torque[:-1], applied[1:data.samples], rtol=0, atol=1e-5)


def test_imported_can_log_needs_its_profile(imported: Path) -> None:
    from dobhil.drives.load import load_profile
    with pytest.raises(ConfigError, match="--drive"):
        read_log(imported)
    with pytest.raises(ConfigError, match="decode as motion feedback of a 'mit' drive"):
        read_log(imported, profile=load_profile("mini-cheetah"))
    with pytest.raises(ConfigError, match="decode as motion feedback of a 'cia402' drive"):
        read_log(imported, profile=load_profile("cia402-emulated"))


def _record(n: int, start: float, *, period: float = 1e-3, protocol: str = "odrive",
            recorded: dict[str, float] | None = None, source: str = "x.mcap") -> IdentData:
    k = np.arange(n, dtype=float)
    return IdentData(period, k * period, 1.0 + k, start + k, 2.0 + k, source, protocol, recorded or {})


def test_join_places_logs_one_after_the_other_with_a_rest_gap() -> None:
    from dobhil.identify.data import JOIN_GAP, Part, join
    a = _record(50, 0.0, source="a.mcap", recorded={"plant.inertia": 0.25, "environment.stiffness": 0.0})
    b = _record(40, 7.0, source="b.mcap", recorded={"plant.inertia": 0.25, "environment.stiffness": 1e4})
    data, parts = join([(a, (Segment(0, 50, FREE),)), (b, (Segment(0, 20, FREE), Segment(20, 40, CONTACT)))])
    assert parts == (Part("a.mcap", 0, 50, (Segment(0, 50, FREE),)),
                     Part("b.mcap", 50 + JOIN_GAP, 40, (Segment(50 + JOIN_GAP, 70 + JOIN_GAP, FREE),
                                                         Segment(70 + JOIN_GAP, 90 + JOIN_GAP, CONTACT))))
    assert data.samples == 90 + JOIN_GAP and data.source == "a.mcap+b.mcap" and data.protocol == "odrive"
    np.testing.assert_array_equal(data.t, np.arange(data.samples) * 1e-3)
    gap = slice(50, 50 + JOIN_GAP)
    assert (data.torque[gap] == 0.0).all() and (data.velocity[gap] == 0.0).all()
    assert (data.position[gap] == 7.0).all()          # at rest where the next log starts
    np.testing.assert_array_equal(data.torque[50 + JOIN_GAP:], b.torque)
    np.testing.assert_array_equal(data.position[:50], a.position)
    assert dict(data.recorded) == {"plant.inertia": 0.25}   # only what both logs agree on
    assert parts[1].local(parts[1].segments[1], 1e-3) == pytest.approx((0.02, 0.04))
    assert JOIN_GAP > 3 + 1 + 9   # the fit's delay search (3 samples + the one in transit) and smoothing


def test_join_of_one_log_is_that_log_and_mixed_logs_are_refused() -> None:
    from dobhil.identify.data import join
    a = _record(50, 0.0)
    data, parts = join([(a, (Segment(0, 50, FREE),))])
    assert data is a and parts[0].offset == 0
    with pytest.raises(ConfigError, match="same period"):
        join([(a, ()), (_record(50, 0.0, period=2e-3, source="b.mcap"), ())])
    with pytest.raises(ConfigError, match="same drive"):
        join([(a, ()), (_record(50, 0.0, protocol="mit", source="b.mcap"), ())])


# -- a run's log with skipped cycles ------------------------------------------------------------

def _run_from(cycles: dict[int, list[float]], k: int) -> int:
    """How many consecutive cycles with finite values start at ``k``."""
    n = 0
    while k + n in cycles and all(np.isfinite(cycles[k + n])):
        n += 1
    return n


@given(st.lists(st.integers(0, 300), max_size=120, unique=True), st.sets(st.integers(0, 300), max_size=10))
def test_the_longest_gap_free_run_of_cycles_is_found(present: list[int], nan_at: set[int]) -> None:
    from dobhil.identify.data import _longest_run
    cycles = {k: [float(k), math.nan if k in nan_at else 0.0, 1.0] for k in present}
    first, length = _longest_run(cycles)
    assert length == max((_run_from(cycles, k) for k in cycles), default=0)
    if length:
        assert _run_from(cycles, first) == length
        assert all(_run_from(cycles, k) < length for k in cycles if k < first)   # the first of the longest


def test_a_log_with_a_skipped_cycle_fits_its_longest_run_and_says_so() -> None:
    from dobhil.cli.identify_cmd import gaps_note
    from dobhil.identify.data import _samples
    cycles = {k: [0.01 * k, 1.0, 0.5] for k in range(400) if k not in (4, 120)}
    data = _samples(cycles, 1e-3, "/tmp/run.mcap", "odrive", {})
    assert (data.first_cycle, data.samples, data.cycles) == (121, 279, 398)
    assert data.position[0] == 0.01 * 121 and data.t[0] == 0.0
    note = gaps_note(data)
    assert "cycles 121-399 of the 398 recorded" in note and "times are from cycle 121" in note
    whole = _samples({k: [0.01 * k, 1.0, 0.5] for k in range(400)}, 1e-3, "run.mcap", "odrive", {})
    assert gaps_note(whole) == "" and whole.first_cycle == 0 and whole.samples == 400
    with pytest.raises(LogFileError, match="30 consecutive usable control cycles at most \\(of 59"):
        _samples({k: [0.0, 0.0, 0.0] for k in range(60) if k != 29}, 1e-3, "short.mcap", "odrive", {})


def test_a_motion_frame_lost_breaks_the_samples(logs: dict[str, Path], tmp_path: Path) -> None:
    """One encoder frame taken out of the candump log, 40 % in: the samples break at its
    deadline (dobhil/identify/period.py numbers the frames by deadline), so the longest
    unbroken run is the 60 % after it, not the whole log shifted by one sample."""
    from dobhil.cli.main import main
    from dobhil.drives.load import load_profile
    from dobhil.drives.odrive import codec
    from dobhil.drives.odrive.codec import CmdId
    dumped = tmp_path / "c.log"
    assert main(["log", "export", str(logs["contact"]), "--can", "--format", "candump", "-o", str(dumped)]) == 0
    encoder = f" {codec.arbitration_id(3, CmdId.GET_ENCODER_ESTIMATES):03X}#"
    lines = dumped.read_text(encoding="utf-8").splitlines(keepends=True)
    motion = [i for i, line in enumerate(lines) if encoder in line]
    lost = motion[int(0.4 * len(motion))]
    (tmp_path / "lost.log").write_text("".join(lines[:lost] + lines[lost + 1:]), encoding="utf-8")
    for name in ("c", "lost"):
        assert main(["log", "import", str(tmp_path / f"{name}.log"), "-o", str(tmp_path / f"{name}.mcap")]) == 0
    profile = load_profile("odrive-0.6")
    whole, broken = (read_log(tmp_path / f"{name}.mcap", profile=profile) for name in ("c", "lost"))
    assert whole.period == broken.period == 1e-3
    assert whole.samples == len(motion) and whole.first_cycle == 0
    after = len(motion) - int(0.4 * len(motion)) - 1
    assert (broken.samples, broken.first_cycle) == (after, int(0.4 * len(motion)) + 1)
    np.testing.assert_array_equal(broken.position, whole.position[-after:])
