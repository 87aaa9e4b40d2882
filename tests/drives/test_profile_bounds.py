"""Drive-profile values have physically meaningful bounds (drivers/README.md): a value
outside them is one line naming the key, the value and the allowed range (exit 2 from
the CLI), never a run that hangs -- a heartbeat every 1e-9 s made the lockstep emulator
emit a million frames per simulated millisecond, an enable timeout of 1e300 s waited
forever."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import pytest
from dobhil_forks import DobhilForks
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.drives import profile as profile_module
from dobhil.drives.load import load_profile, profile_from_mapping
from dobhil.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
SHIPPED = yaml.safe_load((REPO / "drivers" / "odrive-0.6.yaml").read_text(encoding="utf-8"))

#: key -> (lowest, highest, 0 allowed as "off"), as drivers/README.md documents them
BOUNDS: dict[str, tuple[float, float, bool]] = {
    "torque_limit": (math.nextafter(0.0, 1.0), 1e4, False),
    "velocity_limit": (math.nextafter(0.0, 1.0), 1e4, False),
    "feedback_period": (1e-5, 10.0, False),
    "heartbeat_period": (1e-3, 10.0, False),
    "watchdog_timeout": (1e-3, 60.0, True),
    "enable_timeout": (1e-3, 60.0, False),
}

NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6),
                    st.sampled_from([1e-9, 1e300, -0.0, 1e-5, 1e-3, 10.0, 60.0, 1e4]))


def allowed(key: str, value: float) -> bool:
    low, high, off = BOUNDS[key]
    return math.isfinite(value) and (low <= value <= high or (off and value == 0))


@settings(max_examples=400, derandomize=True, deadline=None, database=None)
@given(key=st.sampled_from(sorted(BOUNDS)), value=NUMBERS)
def test_numeric_keys_accept_exactly_their_bounds(key: str, value: float) -> None:
    data = {**SHIPPED, key: value}
    if allowed(key, value):
        assert getattr(profile_from_mapping(data), key) == float(value)
        return
    with pytest.raises(ConfigError) as exc:
        profile_from_mapping(data, source="p.yaml")
    text = str(exc.value)
    assert text.startswith(f"p.yaml: {key}: expected ") and "\n" not in text, text


@settings(max_examples=200, derandomize=True, deadline=None, database=None)
@given(value=st.integers(-2**40, 2**40))
def test_node_id_fits_a_29_bit_can_id_and_the_protocol_narrows_it(value: int) -> None:
    """The common rule first (29 bits), then the protocol's own (ODrive: 6 bits)."""
    data = {**SHIPPED, "node_id": value}
    if 0 <= value <= 63:
        assert profile_from_mapping(data).node_id == value
    elif 0 <= value < 2**29:
        with pytest.raises(ConfigError, match=f"^p.yaml: node_id: expected 0..63 for ODrive, got {value}$"):
            profile_from_mapping(data, source="p.yaml")
    else:
        with pytest.raises(ConfigError, match="node_id: expected an integer from 0 to 536870911"):
            profile_from_mapping(data)


def test_a_profile_built_in_code_is_bounded_too() -> None:
    """dataclasses.replace (the tests', an embedding program's way) checks the same."""
    shipped = load_profile("odrive-0.6")
    with pytest.raises(ConfigError, match="heartbeat_period: expected a number from 0.001 to 10 s, got 1e-09"):
        dataclasses.replace(shipped, heartbeat_period=1e-9)
    with pytest.raises(ConfigError, match="enable_timeout: expected a number from 0.001 to 60 s"):
        dataclasses.replace(shipped, enable_timeout=1e300)


def test_the_documented_bounds_are_the_code_s() -> None:
    """drivers/README.md's table and this test's BOUNDS say what the code enforces."""
    readme = (REPO / "drivers" / "README.md").read_text(encoding="utf-8")
    assert profile_module.MIN_FRAME_PERIOD == BOUNDS["feedback_period"][0]
    assert profile_module.MIN_HEARTBEAT == BOUNDS["heartbeat_period"][0]
    for key, (_low, high, _off) in BOUNDS.items():
        row = next(line for line in readme.splitlines() if line.startswith(f"| `{key}` |"))
        assert f"{high:g}" in row, (key, row)


HOSTILE: list[tuple[str, Any, list[str]]] = [
    ("heartbeat_period", 1e-9, ["run", "--emulate", "--lockstep"]),
    ("enable_timeout", 1e300, ["run", "--bus", "virtual:dobhil-hostile", "--no-preflight"]),
    ("feedback_period", 1e-9, ["emulate", "--bus", "virtual:dobhil-hostile", "--duration", "1"]),
    ("watchdog_timeout", 1e-9, ["run", "--emulate"]),
]


@pytest.mark.parametrize(("key", "value", "args"), HOSTILE, ids=[h[0] for h in HOSTILE])
def test_hostile_profile_values_are_one_line_and_exit_2(tmp_path: Path, key: str, value: Any, args: list[str],
                                                        dobhil_forks: DobhilForks) -> None:
    path = tmp_path / "hostile.yaml"
    path.write_text(yaml.safe_dump({**SHIPPED, "bus": {}, key: value}), encoding="utf-8")
    command, *rest = args
    proc = dobhil_forks.run([command, str(REPO / "configs" / "demo.yaml"), "--set", f"drive.profile={path}", *rest],
                            REPO, timeout=120)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and proc.stdout == "", proc.stderr
    assert lines[0].startswith(f"dobhil {command}: error: {path}: {key}: expected "), lines[0]


BUS_RATES_ALLOWED = (r"bus: expected a mapping of can.Bus keyword arguments \(its bitrate: a whole number "
                     r"from 1 to 1000000 bit/s, the nominal rate of classic CAN and CAN FD; its data_bitrate: "
                     r"a whole number from 1 to 25000000 bit/s, at least its bitrate\), got ")


@pytest.mark.parametrize(("rate", "top"), [("abc", 0), (-5, 0), (0, 0), (1.5, 0), (1e300, 0), (True, 0),
                                           (10**9, 0), (2_000_000, 5_000_000)])
@pytest.mark.parametrize("key", ["bitrate", "data_bitrate"])
def test_a_bus_bit_rate_is_a_whole_number_of_bit_per_s(key: str, rate: Any, top: int) -> None:
    """The profile's ``bus`` goes to can.Bus as it is; its rates are checked here first. The
    nominal rate (``bitrate``) of classic CAN and of CAN FD's arbitration phase is at most
    1 Mbit/s (ISO 11898-1); only a CAN FD data phase (``data_bitrate``) runs faster."""
    if key == "data_bitrate" and rate == 2_000_000:
        rate = 30_000_000
    with pytest.raises(ConfigError, match=BUS_RATES_ALLOWED):
        profile_from_mapping({**SHIPPED, "bus": {**SHIPPED["bus"], key: rate}}, source="p.yaml")
    good = 1_000_000 if key == "bitrate" else 5_000_000
    assert profile_from_mapping({**SHIPPED, "bus": {**SHIPPED["bus"], key: good}}, source="p.yaml").bus[key] == good


def test_a_can_fd_data_phase_slower_than_the_nominal_one_is_refused() -> None:
    """Bit rate switching only speeds the data phase up (ISO 11898-1): a data_bitrate below
    the bitrate was accepted, and the bus budget then counted FD frames longer than classic ones."""
    with pytest.raises(ConfigError, match=BUS_RATES_ALLOWED):
        profile_from_mapping({**SHIPPED, "bus": {"bitrate": 1_000_000, "data_bitrate": 500_000}}, source="p.yaml")
    equal = profile_from_mapping({**SHIPPED, "bus": {"bitrate": 500_000, "data_bitrate": 500_000}}, source="p.yaml")
    assert equal.bus["data_bitrate"] == 500_000


@pytest.mark.parametrize("command", [["analyze"], ["run", "--emulate", "--lockstep", "--duration", "0.01"]])
def test_a_config_bit_rate_no_bus_runs_at_is_one_line(command: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """drive.bitrate is the nominal rate: 1e9 bit/s was accepted (a budget of 0.0 % of
    1000 Mbit/s); above 1 Mbit/s it is refused in one line naming the allowed range."""
    from dobhil.cli.main import main
    assert main([command[0], "demo", *command[1:], "--set", "drive.bitrate=1000000000"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "drive.bitrate = 1000000000: out of range; allowed: >= 0 and <= 1e+06 bit/s" in err[0], err
