"""Bad config input of any shape is one ConfigError line, never a traceback (hypothesis, fixed
seed, bounded examples); huge, NaN and 400-digit numbers; duplicate YAML keys; drive profiles
read numbers as YAML 1.2 does."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.cli.main import main
from dobhil.config import Config, build_config, key_fields, load_config
from dobhil.config.load import MAX_INT, MAX_MAGNITUDE
from dobhil.drives.load import load_profile
from dobhil.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
KEYS = sorted(key_fields())
BOUNDED = settings(max_examples=300, derandomize=True, deadline=None, database=None,
                   suppress_health_check=[HealthCheck.too_slow])

numbers = st.one_of(
    st.integers(), st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e308, -1e308, 1e-320, 5e-324, 1e15, 1e16]),
)
special = st.sampled_from(["1e400", "-1e400", "nan", "inf", "1e-9", "0x10", "1_000", ".5", "csv", "",
                           float("inf"), float("nan"), 10**400, -(10**19), 2**63, 1e300])
scalars = st.one_of(numbers, special, st.booleans(), st.none(), st.text(max_size=20))
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=3)
                      | st.dictionaries(st.text(max_size=5), inner, max_size=3), max_leaves=6)


def _accepted(config: Config) -> None:
    """What a Config that loaded must satisfy: every number finite and in range."""
    for name, value in config.flat().items():
        if isinstance(value, float):
            assert math.isfinite(value) and abs(value) <= MAX_MAGNITUDE, (name, value)
        elif isinstance(value, int):
            assert abs(value) <= MAX_INT, (name, value)


def _one_line(exc: ConfigError) -> str:
    text = str(exc)
    assert text and "\n" not in text, text
    return text


def _loads_or_names_the_key(name: str, value: Any) -> None:
    try:
        _accepted(build_config({name: value}))
    except ConfigError as exc:
        assert name in _one_line(exc)   # a constraint between keys names both


@BOUNDED
@given(name=st.sampled_from(KEYS), value=st.one_of(numbers, special))
def test_any_number_for_any_key_loads_or_is_one_config_error(name: str, value: Any) -> None:
    _loads_or_names_the_key(name, value)


@BOUNDED
@given(name=st.sampled_from(KEYS), value=values)
def test_any_value_of_any_key_loads_or_is_one_config_error(name: str, value: Any) -> None:
    _loads_or_names_the_key(name, value)


@BOUNDED
@given(name=st.one_of(st.sampled_from(KEYS), st.text(max_size=30)), text=st.text(max_size=40))
def test_any_set_string_loads_or_is_one_config_error(name: str, text: str) -> None:
    for item in (f"{name}={text}", text):
        try:
            _accepted(load_config(None, [item]))
        except ConfigError as exc:
            _one_line(exc)


@BOUNDED
@given(document=st.one_of(st.dictionaries(st.sampled_from(["plant", "design", "loop", "sensor", "x"]),
                                          st.dictionaries(st.sampled_from([k.split(".")[1] for k in KEYS]),
                                                          values, max_size=4), max_size=3),
                          values))
def test_any_yaml_file_loads_or_is_one_config_error(document: Any, tmp_path_factory: pytest.TempPathFactory) -> None:
    path = tmp_path_factory.mktemp("cfg") / "c.yaml"
    path.write_text(yaml.safe_dump(document))
    try:
        _accepted(load_config(path))
    except ConfigError as exc:
        _one_line(exc)


@BOUNDED
@given(text=st.text(max_size=200))
def test_any_file_text_loads_or_is_one_config_error(text: str, tmp_path_factory: pytest.TempPathFactory) -> None:
    path = tmp_path_factory.mktemp("cfg") / "c.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        _accepted(load_config(path))
    except ConfigError as exc:
        _one_line(exc)


@pytest.mark.parametrize(("item", "message"), [
    ("sensor.seed=1e400", "sensor.seed = '1e400': must be a finite number"),
    ("plant.initial_position=1e308", "outside the physical range"),
    ("plant.inertia=" + "9" * 400, "an integer of 400 digits>: outside the physical range"),
    ("sensor.seed=" + "9" * 400, "sensor.seed = <an integer of 400 digits>: too large"),
    ("plant.inertia=" + "9" * 5000, "must be a finite number"),
    ("design.force_gain=.nan", "must be a finite number"),
    ("loop.period=-.inf", "must be a finite number"),
    ("sensor.seed=2.5", "must be a whole number"),
])
def test_huge_and_nan_numbers_on_the_command_line(item: str, message: str,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "demo", "--set", item]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err
    assert len(err) < 300


@pytest.mark.parametrize("override", ["loop=1", "plant=0.3"])
def test_a_section_given_a_value_says_it_is_a_section(override: str) -> None:
    """Not "unknown config key 'loop'": the name is known, as a section that needs keys."""
    section = override.split("=")[0]
    with pytest.raises(ConfigError, match=rf"^'{section}' is a config section, not a key: give {section}.KEY "):
        load_config(None, [override])


def test_a_huge_profile_name_is_shortened_in_its_one_line() -> None:
    """A 100,000-character drive.profile was quoted whole, twice: a 200 KB "line"."""
    from dobhil.drives.load import load_drive_profile
    with pytest.raises(ConfigError) as info:
        load_drive_profile(load_config(None, ["drive.profile=" + "x" * 100_000]))
    assert len(str(info.value)) < 1000 and "\n" not in str(info.value)


def test_a_realtime_priority_past_linuxs_range_is_refused() -> None:
    """SCHED_FIFO priorities are 1-99 on Linux: 1000 was clamped to 99 without a word."""
    assert load_config(None, ["loop.realtime_priority=99"]).loop.realtime_priority == 99
    with pytest.raises(ConfigError, match=r"^loop.realtime_priority = 1000: out of range; allowed: >= 0 and <= 99$"):
        load_config(None, ["loop.realtime_priority=1000"])


@pytest.mark.parametrize("name", ["loop.cpu_affinity", "drive.node_id"])
def test_below_the_none_value_of_minus_one_is_refused(name: str) -> None:
    """-1 stands for "none" (no pinning, the profile's node id); -5 was taken as -1 without a word."""
    assert load_config(None, [f"{name}=-1"]).flat()[name] == -1
    with pytest.raises(ConfigError, match=rf"^{name} = -5: out of range; allowed: >= -1; .*\(-1: "):
        load_config(None, [f"{name}=-5"])


def test_a_cpu_past_the_machines_is_refused_by_the_run(capsys: pytest.CaptureFixture[str]) -> None:
    """The config cannot know the machine's CPUs: the run refuses one it may not use, before it starts."""
    cpu = max(os.sched_getaffinity(0)) + 1 if hasattr(os, "sched_getaffinity") else None
    if cpu is None:
        pytest.skip("no CPU affinity here")
    assert main(["run", "demo", "--emulate", "--duration", "0.05", "--set", f"loop.cpu_affinity={cpu}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"loop.cpu_affinity = {cpu}: not a CPU this process may use" in err, err


def test_numbers_in_range_still_load() -> None:
    config = load_config(None, ["sensor.seed=1e3", "plant.initial_position=-1e-3", "environment.stiffness=1e9",
                                "sensor.seed=" + str(2**63 - 1)])
    assert config.sensor.seed == 2**63 - 1 and config.environment.stiffness == 1e9


@pytest.mark.parametrize(("text", "line", "first"), [
    ("design:\n  force_gain: 1\n  dob_bandwidth: 100\n  force_gain: 3\n", 4, 2),
    ("plant:\n  inertia: 0.2\ndesign: {force_gain: 1}\nplant:\n  inertia: 0.3\n", 4, 1),
    ("design: {force_gain: 1, force_gain: 2}\n", 1, 1),
])
def test_duplicate_yaml_keys_are_rejected_with_their_lines(text: str, line: int, first: int,
                                                           tmp_path: Path) -> None:
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    pattern = rf"at line {line}, column \d+: duplicate key '\w+' \(first at line {first}\)"
    with pytest.raises(ConfigError, match=pattern):
        load_config(path)


@pytest.mark.parametrize("text", [
    "loop:\n  duration: 1.2\nloop.duration: 0.25\n",
    "loop.duration: 0.25\nloop: {duration: 1.2, period: 0.001}\n",
])
def test_a_key_given_as_a_section_key_and_dotted_is_a_duplicate(text: str, tmp_path: Path) -> None:
    """YAML sees two keys (``loop`` and ``loop.duration``); the config one, given twice."""
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"^loop.duration: given twice in one mapping .*; give it once$"):
        load_config(path)


def test_yaml_merge_keys_are_not_duplicates(tmp_path: Path) -> None:
    path = tmp_path / "merge.yaml"
    path.write_text("plant: &p {inertia: 0.3}\nenvironment: {stiffness: 5.0}\n"
                    "design:\n  <<: {force_gain: 4.0}\n  dob_bandwidth: 100\n")
    config = load_config(path)
    assert config.design.force_gain == 4.0 and config.plant.inertia == 0.3


def _profile(tmp_path: Path, **changes: str) -> Path:
    text = (ROOT / "drivers" / "odrive-0.6.yaml").read_text()
    keys = [line.split(":")[0] for line in text.splitlines()]
    lines = [f"{k}: {changes[k]}" if k in changes else line for k, line in zip(keys, text.splitlines())]
    path = tmp_path / "p.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_profile_reads_2e_minus_2_as_a_number(tmp_path: Path) -> None:
    profile = load_profile(_profile(tmp_path, watchdog_timeout="2e-2", feedback_period="1e-3"))
    assert profile.watchdog_timeout == 2e-2 and profile.feedback_period == 1e-3


@pytest.mark.parametrize(("value", "message"), [
    ("9" * 400, "torque_limit: expected a number > 0 and <= 10000 Nm, got inf"),
    ("9" * 5000, "cannot read drive profile"),
    (".nan", "got nan"),
    ("1e400", "got inf"),
    ("fast", "got 'fast'"),
])
def test_a_bad_profile_number_is_one_line(value: str, message: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=message) as exc:
        load_profile(_profile(tmp_path, torque_limit=value))
    assert "\n" not in str(exc.value) and len(str(exc.value)) < 300


def test_a_duplicate_profile_key_names_its_lines(tmp_path: Path) -> None:
    path = _profile(tmp_path)
    path.write_text(path.read_text() + "node_id: 4\n")
    with pytest.raises(ConfigError, match=r"YAML error in drive profile at line \d+, column 1: "
                                          r"duplicate key 'node_id' \(first at line \d+\)"):
        load_profile(path)
