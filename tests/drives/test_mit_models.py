"""The MIT model table (drivers/mit-models.yaml) and its loader (dobhil.drives.mit.models):
every row sourced and consistent with the published clients it cites, the shipped MIT
profiles name rows within their ranges, and every bad table is one ConfigError line naming
the file, the row and the key."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from dobhil.config.yamlio import safe_load
from dobhil.data import DRIVER_TABLES, drivers_dir, shipped_profiles
from dobhil.drives.mit.codec import Special
from dobhil.drives.mit.models import MODELS_FILE, find_model, load_models, shipped_models_path
from dobhil.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
TABLE = REPO / "drivers" / MODELS_FILE


def test_the_table_ships_with_the_profiles_and_is_not_one() -> None:
    assert shipped_models_path() == drivers_dir() / MODELS_FILE and shipped_models_path().is_file()
    assert shipped_models_path().read_bytes() == TABLE.read_bytes()
    assert "mit-models" in DRIVER_TABLES and "mit-models" not in shipped_profiles()
    assert {"ak80-9", "ak70-10", "ak10-9", "dm4310", "dm8009", "mini-cheetah"} <= set(shipped_profiles())


def test_every_row_cites_its_source_and_the_required_models_are_there() -> None:
    table = load_models()
    for model in table.values():
        assert model.source and model.key == (model.vendor, model.model, model.firmware)
        assert model.kp_max == 500.0 and model.kd_max == 5.0  # every source agrees
        assert Special.ENTER in model.special and Special.EXIT in model.special and Special.ZERO in model.special
        assert (Special.CLEAR_ERROR in model.special) == (model.vendor == "damiao")
    required = {("cubemars", "AK80-9"), ("cubemars", "AK70-10"), ("cubemars", "AK10-9"), ("damiao", "DM4310"),
                ("damiao", "DM8009"), ("mini-cheetah", "motorcontrol")}
    assert required <= {(v, m) for v, m, _ in table}
    # firmware variants where ranges, direction or reply differ
    assert {f for v, m, f in table if m == "AK80-9"} == {"manual-1.0.8", "2.0", "1.1"}
    assert {f for v, m, f in table if m == "AK10-9"} == {"manual-1.0.8", "1.1"}
    ak = find_model("cubemars", "AK80-9", "manual-1.0.8")
    assert (ak.p_max, ak.v_max, ak.t_max, ak.layout.name, ak.axis_direction) == (12.5, 50.0, 18.0, "cubemars", 1)
    assert find_model("cubemars", "AK10-9", "1.1").axis_direction == -1
    cheetah = find_model("mini-cheetah", "motorcontrol", "3586419")
    assert (cheetah.v_max, cheetah.t_max, cheetah.command_timeout, cheetah.layout.lengths) == (65.0, 40.0, 0.025,
                                                                                               (6, 7))
    assert find_model("damiao", "DM4310", "factory").layout.max_motor_id == 15
    assert load_models() is load_models()  # cached while the file is unchanged


def test_rows_agree_with_damiao_motor() -> None:
    """damiao-motor's MOTOR_TYPE_PRESETS (Damiao's Limit_Param table) for every DM row."""
    motor = pytest.importorskip("damiao_motor.core.motor")
    rows = [m for m in load_models().values() if m.vendor == "damiao"]
    assert len(rows) >= 2
    for row in rows:
        preset = motor.MOTOR_TYPE_PRESETS[row.model.removeprefix("DM")]
        assert (preset["p_max"], preset["v_max"], preset["t_max"]) == (row.p_max, row.v_max, row.t_max)
        assert (motor.KP_MAX, motor.KD_MAX) == (row.kp_max, row.kd_max)
    states = find_model("damiao", "DM4310", "factory").layout.states
    assert states[motor.DM_MOTOR_ENABLED] == "enabled" and states[motor.DM_MOTOR_DISABLED] == "disabled"
    assert set(states) == set(motor._STATE_NAME_MAP)  # the client's table of state codes


def test_older_firmware_rows_agree_with_canmotorlib() -> None:
    lib = pytest.importorskip("motor_driver.canmotorlib")
    pairs = {("AK80-9", "2.0"): lib.AK80_9_V2_PARAMS, ("AK80-9", "1.1"): lib.AK80_9_V1p1_PARAMS,
             ("AK70-10", "1.1"): lib.AK70_10_V1p1_params, ("AK10-9", "1.1"): lib.AK10_9_V1p1_PARAMS,
             ("AK80-6", "2.0"): lib.AK80_6_V2_PARAMS, ("AK80-6", "1.1"): lib.AK80_6_V1p1_PARAMS,
             ("AK80-6", "1.0"): lib.AK80_6_V1_PARAMS}
    for (model, firmware), params in pairs.items():
        row = find_model("cubemars", model, firmware)
        assert (row.p_max, row.v_max, row.t_max, row.kp_max, row.kd_max, row.axis_direction) == (
            params["P_MAX"], params["V_MAX"], params["T_MAX"], params["KP_MAX"], params["KD_MAX"],
            params["AXIS_DIRECTION"]), (model, firmware)
        assert params["P_MIN"] == -row.p_max and params["KP_MIN"] == 0
    # canmotorlib reads 6 bytes, except AK10-9 V1.1 ("also sends back temperature data and an error code")
    assert find_model("cubemars", "AK10-9", "1.1").layout.lengths == (8,)
    assert find_model("cubemars", "AK80-9", "1.1").layout.lengths == (6,)


def test_current_firmware_rows_agree_with_tmotorcancontrol_but_the_ak60_6() -> None:
    """tmotorcancontrol's MIT_Params and the CubeMars manual V1.0.8 agree but for the
    AK60-6's velocity (45 in the manual, 50 there): the row follows the manual and says so."""
    mit_can = pytest.importorskip("TMotorCANControl.mit_can")
    for name, params in mit_can.MIT_Params.items():
        if name == "ERROR_CODES":
            continue
        row = find_model("cubemars", name, "manual-1.0.8")
        assert (row.p_max, row.t_max, row.kp_max, row.kd_max) == (params["P_max"], params["T_max"],
                                                                  params["Kp_max"], params["Kd_max"])
        if name == "AK60-6":
            assert (row.v_max, params["V_max"]) == (45.0, 50.0) and "disagree" in row.note
        else:
            assert row.v_max == params["V_max"]
    errors = find_model("cubemars", "AK80-9", "manual-1.0.8").layout.errors
    assert set(errors) == set(mit_can.MIT_Params["ERROR_CODES"]) - {0}


@pytest.mark.parametrize("name", ["ak80-9", "ak80-9-2.0", "ak80-9-1.1", "ak70-10", "ak70-10-1.1", "ak10-9",
                                  "ak10-9-1.1", "dm4310", "dm8009", "mini-cheetah"])
def test_each_shipped_mit_profile_names_a_row_within_its_ranges(name: str) -> None:
    """Read as YAML (the profile's rules live with the drive): protocol mit, a row of the
    table, torque and velocity limits within its ranges, one period of command delay."""
    data = safe_load((REPO / "drivers" / f"{name}.yaml").read_text())
    assert data["protocol"] == "mit" and data["command_delay_periods"] == 1
    assert "feedback_period" not in data and "heartbeat_period" not in data
    row = find_model(data["mit"]["vendor"], data["mit"]["model"], data["firmware"])
    assert 0 < data["torque_limit"] <= row.t_max and 0 < data["velocity_limit"] < row.v_max
    assert 1 <= data["node_id"] <= row.layout.max_motor_id


def test_a_missing_row_names_what_the_table_has() -> None:
    with pytest.raises(ConfigError) as err:
        find_model("cubemars", "AK99-1", "x")
    assert str(err.value) == ("mit.model: no row for cubemars AK99-1 firmware 'x' in drivers/mit-models.yaml; "
                              "known: cubemars models: AK10-9, AK60-6, AK70-10, AK80-6, AK80-64, AK80-9")
    with pytest.raises(ConfigError, match=r"known: cubemars AK80-9 has firmware '1.1', '2.0', 'manual-1.0.8'$"):
        find_model("cubemars", "AK80-9", "9.9")
    with pytest.raises(ConfigError, match=r"known: vendors: cubemars, damiao, mini-cheetah$"):
        find_model("acme", "X1", "1")


def _table(tmp_path: Path, change: Any = None, text: str | None = None) -> Path:
    data = yaml.safe_load(TABLE.read_text())
    if change is not None:
        change(data)
    path = tmp_path / "models.yaml"
    path.write_text(text if text is not None else yaml.safe_dump(data))
    return path


def _row(key: str, value: Any) -> Any:
    def change(data: dict[str, Any]) -> None:
        data["models"][0][key] = value
    return change


def _drop(key: str) -> Any:
    def change(data: dict[str, Any]) -> None:
        del data["models"][0][key]
    return change


ROW0 = r"models\[0\] \(cubemars AK80-9 firmware 'manual-1.0.8'\)"


@pytest.mark.parametrize(("change", "message"), [
    (_row("t_max", -1), ROW0 + r": t_max: expected a number > 0 and <= 100000, got -1$"),
    (_row("p_max", "a lot"), ROW0 + r": p_max: expected a number > 0 and <= 100000, got 'a lot'$"),
    (_row("kd_max", float("nan")), ROW0 + r": kd_max: expected a number"),
    (_row("reply", "mystery"), ROW0 + r": reply: expected one of .*mbed.* \(reply_layouts\), got 'mystery'$"),
    (_row("position_at_limit", "bounce"), ROW0 + r": position_at_limit: expected wrap or saturate, got 'bounce'$"),
    (_row("axis_direction", 2), ROW0 + r": axis_direction: expected 1 or -1, got 2$"),
    (_row("axis_direction", True), ROW0 + r": axis_direction: expected 1 or -1, got True$"),
    (_row("command_timeout", 0), ROW0 + r": command_timeout: expected a number > 0 and <= 60, got 0$"),
    (_row("special", ["enter", "fly"]), ROW0 + r": special: expected a list of clear_error, enter, exit, zero"),
    (_row("firmware", 2.0), r"models\[0\]: firmware: expected a non-empty string \(quote a version: \"2.0\"\)"),
    (_row("colour", "red"), ROW0 + r": unknown key 'colour' \(allowed: vendor, model"),
    (_drop("source"), ROW0 + r": missing key 'source'$"),
    (lambda d: d["models"].append(dict(d["models"][0])),
     r"models\[21\]: cubemars AK80-9 firmware 'manual-1.0.8' is given twice$"),
    (lambda d: d["reply_layouts"]["cubemars"].update(lengths=[9]), r"reply_layouts.cubemars: reply layout cubemars: "
     r"lengths \(9,\): expected 6 to 8 bytes$"),
    (lambda d: d["reply_layouts"]["cubemars"].update(id="byte3"), r"reply_layouts.cubemars: .*id 'byte3'"),
    (lambda d: d["reply_layouts"]["cubemars"]["extra"].update(error=9), r"extra error: byte 9 is not in"),
    (lambda d: d.pop("models"), r"missing key 'models'$"),
    (lambda d: d.update(rows=[]), r"unknown key 'rows' \(allowed: reply_layouts, models\)$"),
])
def test_a_bad_table_is_one_line_naming_file_row_and_key(tmp_path: Path, change: Any, message: str) -> None:
    path = _table(tmp_path, change)
    with pytest.raises(ConfigError, match=message) as err:
        load_models(path)
    assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)


def test_unreadable_tables(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope.yaml: cannot read the MIT model table: No such file"):
        load_models(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=r"YAML error in the MIT model table at line 3"):
        load_models(_table(tmp_path, text="models:\n  - {a: 1\n"))
    with pytest.raises(ConfigError, match=r"duplicate key 'models'"):
        load_models(_table(tmp_path, text="models: []\nmodels: []\n"))
    with pytest.raises(ConfigError, match=r"expected a mapping of reply_layouts, models, got \[1\]"):
        load_models(_table(tmp_path, text="[1]\n"))


def test_an_edited_table_is_read_again(tmp_path: Path) -> None:
    path = _table(tmp_path)
    assert load_models(path)[("cubemars", "AK80-9", "manual-1.0.8")].t_max == 18.0
    _table(tmp_path, _row("t_max", 12.0))
    assert find_model("cubemars", "AK80-9", "manual-1.0.8", path).t_max == 12.0
