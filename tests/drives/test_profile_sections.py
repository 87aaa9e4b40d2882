"""The drive seam's profile side: a protocol's section validated by its own rules (one
validator, one error style), the renamed period keys, and protocols found through the
entry-point group ``dobhil.drives`` -- shown with a REAL discovery: a throwaway
distribution (``*.dist-info`` with ``entry_points.txt``) and its module written to a
temporary directory put on ``sys.path``, a protocol dobhil never heard of."""

from __future__ import annotations

import dataclasses
import pickle
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from dobhil_forks import DobhilForks
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.drives import load_profile, make_drive
from dobhil.drives.odrive.drive import ODriveDrive
from dobhil.drives.load import profile_from_mapping
from dobhil.drives.profile import RENAMED_KEYS
from dobhil.drives.registry import ENTRY_POINT_GROUP, drive_class, protocols
from dobhil.drives.emulated import EmulatedDrive
from dobhil.drives.registry import emulated_protocols, emulator_class
from dobhil.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
SHIPPED = yaml.safe_load((REPO / "drivers" / "odrive-0.6.yaml").read_text(encoding="utf-8"))

#: the module of the throwaway distribution: a drive and an emulated drive of protocol
#: "acmebus", its section rules written with the public Rule helpers
PLUGIN_MODULE = '''
import can
from dobhil.drives.base import Drive
from dobhil.drives.profile import ProtocolRules, Rule
from dobhil.drives.emulated import EmulatedDrive
from dobhil.drives.plugin import DriveProtocol


class AcmeDrive(Drive):
    protocol = "acmebus"
    profile_rules = ProtocolRules(
        section={"unit": Rule.one_of("mNm", "uNm"),
                 "gain": Rule.number(0.0, 10.0, "", default=1.0),
                 "label": Rule((str,), "a string", lambda v: True, default="")},
        common={"node_id": Rule.integer(1, 127)},
        requires=frozenset({"heartbeat_period"}),
    )

    def _enable_start(self):
        return ()

    def _disable_frames(self):
        return ()

    def _torque_frame(self, tau_nm):
        return can.Message(arbitration_id=0x200 + self.node_id, data=bytes(2), is_extended_id=False)

    def _decode(self, msg):
        return ()


class AcmeEmulator(EmulatedDrive):
    def _on_frame(self, msg):
        pass

    def _on_time(self, now):
        pass

    def _plant_torque(self):
        return 0.0

    def _cyclic_frames(self):
        return ()


class AcmeProtocol(DriveProtocol):
    name = "acmebus"
    title = "Acme bus"

    @property
    def drive_class(self):
        return AcmeDrive

    @property
    def emulator_class(self):
        return AcmeEmulator
'''


def install_plugin(root: Path, entry_points: str, module: str = "acme_dobhil_plugin") -> None:
    """A distribution as pip would leave it: ``<name>-<version>.dist-info/{METADATA,
    entry_points.txt}`` beside the module it names."""
    info = root / "acme_dobhil_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-dobhil-plugin\nVersion: 0.1\n",
                                   encoding="utf-8")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n{entry_points}", encoding="utf-8")
    (root / f"{module}.py").write_text(PLUGIN_MODULE, encoding="utf-8")


@pytest.fixture
def plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    install_plugin(tmp_path, "acmebus = acme_dobhil_plugin:AcmeProtocol\n"
                             "broken = acme_no_such_module:Nope\n"
                             "odrive = acme_dobhil_plugin:AcmeProtocol\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("acme_dobhil_plugin", None)


def acme_profile(tmp_path: Path, **changes: Any) -> Path:
    data = {"protocol": "acmebus", "firmware": "1.0", "node_id": 5, "torque_limit": 2.0,
            "velocity_limit": 50.0, "enable_timeout": 1.0, "heartbeat_period": 0.1,
            "acmebus": {"unit": "uNm"}}
    data.update(changes)
    path = tmp_path / "acme.yaml"
    path.write_text(yaml.safe_dump({k: v for k, v in data.items() if v is not None}), encoding="utf-8")
    return path


def one_line(exc: pytest.ExceptionInfo[ConfigError]) -> str:
    text = str(exc.value)
    assert "\n" not in text, text
    return text


# -- entry points: a protocol from another package ------------------------------


def test_a_protocol_of_another_package_is_found_by_its_entry_points(plugin: Path) -> None:
    assert "acmebus" in protocols() and "acmebus" in emulated_protocols()
    profile = load_profile(acme_profile(plugin))
    # its section, validated by its own rules, defaults filled in, read-only
    assert dict(profile.options) == {"unit": "uNm", "gain": 1.0, "label": ""}
    with pytest.raises(TypeError):
        profile.options["unit"] = "mNm"  # type: ignore[index]
    assert profile.directory == str(plugin.resolve())
    bus = can.Bus(interface="virtual", channel="dobhil-test-acme")
    try:
        drive = make_drive(bus, profile, reset_faults=True)
        assert type(drive).__name__ == "AcmeDrive" and drive._reset_faults is True
    finally:
        bus.shutdown()
    emulator = emulator_class("acmebus")
    assert emulator.__name__ == "AcmeEmulator" and issubclass(emulator, EmulatedDrive)


def test_a_built_in_protocol_wins_over_an_entry_point_of_its_name(plugin: Path) -> None:
    assert drive_class("odrive") is ODriveDrive


def test_an_entry_point_that_fails_to_load_is_one_line_naming_it(plugin: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        drive_class("broken")
    assert one_line(exc) == (f"entry point 'broken' (group {ENTRY_POINT_GROUP}) = acme_no_such_module:Nope "
                             "failed to load: ModuleNotFoundError: No module named 'acme_no_such_module'")
    with pytest.raises(ConfigError) as exc:
        load_profile(acme_profile(plugin, protocol="broken", acmebus=None))
    assert one_line(exc).startswith(f"{plugin / 'acme.yaml'}: entry point 'broken' ")


def test_the_section_rules_of_a_plugin_protocol(plugin: Path) -> None:
    path = plugin / "acme.yaml"
    cases = [
        (dict(acmebus={"unit": "Nm"}), f"{path}: acmebus.unit: expected one of 'mNm', 'uNm', got 'Nm'"),
        (dict(acmebus={"unit": "mNm", "gian": 2}),
         f"{path}: unknown key 'acmebus.gian' (allowed in acmebus: unit, gain, label)"),
        (dict(acmebus={"gain": 2.0}), f"{path}: missing key 'acmebus.unit' (one of 'mNm', 'uNm')"),
        (dict(acmebus=None), f"{path}: missing key 'acmebus.unit' (one of 'mNm', 'uNm')"),
        (dict(acmebus={"unit": "mNm", "gain": "high"}),
         f"{path}: acmebus.gain: expected a number from 0 to 10, got 'high'"),
        (dict(acmebus={"unit": "mNm", "label": True}), f"{path}: acmebus.label: expected a string, got True"),
        (dict(acmebus=["unit"]), f"{path}: acmebus: expected a mapping of acmebus settings "
                                 "(unit, gain, label), got ['unit']"),
        (dict(odrive={}), f"{path}: odrive: a section of protocol 'odrive', but this profile's protocol "
                          "is 'acmebus' (its section is acmebus:)"),
        (dict(node_id=0), f"{path}: node_id: expected an integer from 1 to 127, got 0"),
        (dict(heartbeat_period=None),
         f"{path}: missing key 'heartbeat_period' (a number from 0.001 to 10 s; protocol 'acmebus' needs it)"),
    ]
    for changes, message in cases:
        with pytest.raises(ConfigError) as exc:
            load_profile(acme_profile(plugin, **changes))
        assert one_line(exc) == message, changes


def test_an_unknown_protocol_lists_the_known_ones(plugin: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        profile_from_mapping({**SHIPPED, "protocol": "canopenx"}, source="p.yaml")
    assert one_line(exc) == ("p.yaml: protocol: expected one of ['acmebus', 'broken', 'cia402', 'mit', 'moteus', "
                             "'odrive'], got 'canopenx'")


# -- ODrive's rules ---------------------------------------------------------------


def test_odrive_accepts_an_empty_section_and_refuses_keys_in_it() -> None:
    assert profile_from_mapping({**SHIPPED, "odrive": {}}).options == {}
    assert profile_from_mapping({**SHIPPED, "odrive": None}).options == {}
    with pytest.raises(ConfigError) as exc:
        profile_from_mapping({**SHIPPED, "odrive": {"axis": 0}}, source="p.yaml")
    assert one_line(exc) == "p.yaml: unknown key 'odrive.axis' (allowed in odrive: none)"


def test_an_unknown_top_level_key_names_the_allowed_ones() -> None:
    with pytest.raises(ConfigError) as exc:
        profile_from_mapping({**SHIPPED, "cia402x": {}}, source="p.yaml")
    assert one_line(exc) == ("p.yaml: unknown key 'cia402x' (allowed: protocol, firmware, node_id, torque_limit, "
                             "velocity_limit, feedback_period, heartbeat_period, watchdog_timeout, enable_timeout, "
                             "command_delay_periods, bus, name, odrive)")


@pytest.mark.parametrize("key", ["feedback_period", "heartbeat_period"])
def test_odrive_needs_both_periods(key: str) -> None:
    data = {k: v for k, v in SHIPPED.items() if k != key}
    with pytest.raises(ConfigError) as exc:
        profile_from_mapping(data, source="p.yaml")
    assert one_line(exc).startswith(f"p.yaml: missing key {key!r} (a number from ")
    assert one_line(exc).endswith("; protocol 'odrive' needs it)")
    # a profile built in code without it: the drive refuses it when made
    profile = dataclasses.replace(load_profile("odrive-0.6"), **{key: None})
    bus = can.Bus(interface="virtual", channel="dobhil-test-needs")
    try:
        with pytest.raises(ConfigError, match=f"missing key {key!r} \\(protocol 'odrive' needs it\\)"):
            make_drive(bus, profile)
    finally:
        bus.shutdown()


def test_optional_common_keys_and_their_defaults() -> None:
    data = {k: v for k, v in SHIPPED.items() if k not in ("watchdog_timeout", "bus")}
    profile = profile_from_mapping(data)
    assert profile.watchdog_timeout == 0.0 and profile.command_delay_periods is None and profile.bus == {}
    assert profile_from_mapping({**SHIPPED, "command_delay_periods": 1}).command_delay_periods == 1
    assert profile_from_mapping({**SHIPPED, "command_delay_periods": None}).command_delay_periods is None


# -- renamed keys -------------------------------------------------------------------


@pytest.mark.parametrize(("old", "new"), sorted(RENAMED_KEYS.items()))
def test_an_old_key_name_is_refused_naming_the_new_one(old: str, new: str, tmp_path: Path) -> None:
    data = {**SHIPPED, old: SHIPPED[new]}
    del data[new]
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_profile(path)
    assert one_line(exc) == f"{path}: {old}: renamed to {new} (a period in seconds)"
    with pytest.raises(ConfigError) as exc:  # given beside the new name too
        profile_from_mapping({**SHIPPED, old: 0.1}, source="p.yaml")
    assert one_line(exc) == f"p.yaml: {old}: renamed to {new} (a period in seconds)"


@pytest.mark.parametrize("command", ["run", "check"])
def test_the_cli_refuses_an_old_name_profile_in_one_line(command: str, tmp_path: Path,
                                                         dobhil_forks: DobhilForks) -> None:
    data = {**{k: v for k, v in SHIPPED.items() if k != "feedback_period"}, "encoder_msg_rate": 0.001, "bus": {}}
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    rest = ["--emulate", "--lockstep"] if command == "run" else ["--bus", "virtual:dobhil-old-name"]
    proc = dobhil_forks.run([command, str(REPO / "configs" / "demo.yaml"), "--set", f"drive.profile={path}", *rest],
                            REPO, timeout=120)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [
        f"dobhil {command}: error: {path}: encoder_msg_rate: renamed to feedback_period (a period in seconds)"]


# -- the profile object -------------------------------------------------------------


def test_a_profile_with_a_section_pickles_read_only_again(plugin: Path) -> None:
    profile = load_profile(acme_profile(plugin, acmebus={"unit": "mNm", "gain": 2}))
    copy = pickle.loads(pickle.dumps(profile))
    assert copy == profile and dict(copy.options) == {"unit": "mNm", "gain": 2.0, "label": ""}
    with pytest.raises(TypeError):
        copy.options["gain"] = 3.0  # type: ignore[index]


@settings(max_examples=300, derandomize=True, deadline=None, database=None)
@given(section=st.one_of(st.none(), st.dictionaries(st.text(max_size=8), st.integers() | st.text(max_size=4),
                                                     max_size=3),
                         st.lists(st.integers(), max_size=2), st.integers()),
       delay=st.one_of(st.none(), st.integers(-3, 20), st.booleans(), st.floats(allow_nan=True), st.text(max_size=3)))
def test_any_section_and_delay_is_a_profile_or_one_line(section: Any, delay: Any) -> None:
    """Whatever the YAML holds under ``odrive:`` and ``command_delay_periods``: a profile
    exactly when both are acceptable, else one ConfigError line naming the key."""
    data = {**SHIPPED, "odrive": section, "command_delay_periods": delay}
    section_ok = section is None or section == {}
    delay_ok = delay is None or (type(delay) is int and 0 <= delay <= 16)
    if section_ok and delay_ok:
        assert profile_from_mapping(data).command_delay_periods == delay
        return
    with pytest.raises(ConfigError) as exc:
        profile_from_mapping(data, source="p.yaml")
    text = one_line(exc)
    if not delay_ok:  # common keys are checked before the section
        assert text.startswith("p.yaml: command_delay_periods: expected an integer from 0 to 16, got "), text
    else:
        assert text.startswith(("p.yaml: unknown key 'odrive.", "p.yaml: odrive: expected a mapping")), text


def test_a_log_written_before_the_rename_still_replays_its_profile() -> None:
    """A recording keeps the profile as JSON per key; one from before the rename has the
    old names, and it is not the user's to edit: replay reads it under the new ones."""
    import json

    from dobhil.drives.decode import recorded_profile
    old = {k: v for k, v in SHIPPED.items() if k not in ("feedback_period", "heartbeat_period", "bus")}
    old.update(encoder_msg_rate=0.001, heartbeat_msg_rate=0.1)
    profile = recorded_profile({k: json.dumps(v) for k, v in old.items()}, "old.mcap")
    assert (profile.feedback_period, profile.heartbeat_period) == (0.001, 0.1)


# -- the one validator takes its protocols as an argument -------------------------


def test_the_validator_asks_only_the_protocols_it_is_given() -> None:
    """``dobhil.drives.profile`` holds no registry: the rules come from the look-up passed in,
    so a caller (a test, another tool) can validate against protocols the registry lacks, and
    a protocol the look-up lacks is refused although the registry knows it."""
    from dobhil.drives import profile as validator
    from dobhil.drives.profile import ProtocolLookup, ProtocolRules, Rule

    def rules(name: str) -> ProtocolRules:
        if name != "benchbus":
            raise ConfigError(f"protocol: expected one of ['benchbus'], got {name!r}")
        return ProtocolRules(section={"gain": Rule.number(0.0, 2.0, "", default=1.0)})

    lookup = ProtocolLookup(rules=rules, names=lambda: ("benchbus",))
    data = {k: v for k, v in SHIPPED.items() if k != "odrive"}
    made = validator.profile_from_mapping({**data, "protocol": "benchbus", "benchbus": {"gain": 0.5}},
                                          protocols=lookup)
    assert made.protocol == "benchbus" and made.options == {"gain": 0.5}
    with pytest.raises(ConfigError) as exc:
        validator.profile_from_mapping({**data, "protocol": "odrive"}, protocols=lookup, source="p.yaml")
    assert one_line(exc) == "p.yaml: protocol: expected one of ['benchbus'], got 'odrive'"
    assert not hasattr(validator, "use_protocol_lookup") and not hasattr(validator, "_lookup")


def test_the_built_in_table_is_what_pyproject_registers() -> None:
    """The built-in protocols register through the same entry points (``pyproject.toml``);
    the table beside them (for a tree never installed) must name the same classes."""
    import tomllib

    from dobhil.drives.registry import PROTOCOL_CLASSES
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = project["entry-points"][ENTRY_POINT_GROUP]
    assert {name: ":".join(row) for name, row in PROTOCOL_CLASSES.items()} == \
        {name: value for name, value in declared.items() if name in PROTOCOL_CLASSES}
    assert ENTRY_POINT_GROUP == "dobhil.drives"
