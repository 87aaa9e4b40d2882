"""``axes:`` configs (:mod:`dobhil.config.axes`): every refusal is one line naming what was
wrong and what is allowed; a config without ``axes:`` is the one axis load_config reads; and
(hypothesis) each axis' Config is what load_config makes of the top level's keys with the
axis' own over them, written as one single-axis file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.config import load_config
from dobhil.config.axes import SHARED_LOOP_KEYS, SINGLE_AXIS, Coupling, has_axes, load_axes
from dobhil.errors import ConfigError

BOUNDED = settings(max_examples=100, derandomize=True, deadline=None, database=None,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

TWO_AXES: dict[str, Any] = {
    "loop": {"period": 0.001, "duration": 0.5, "timing": "lockstep"},
    "design": {"force_gain": 3.0},
    "axes": [{"name": "left", "drive": {"profile": "odrive-0.6", "node_id": 1}},
             {"name": "right", "drive": {"profile": "odrive-0.6", "node_id": 2}, "plant": {"inertia": 0.3}}],
    "environment": {"stiffness": 500.0,
                    "coupling": [{"axes": ["left", "right"], "stiffness": 2000.0, "damping": 20.0}]},
}


def write(tmp_path: Path, data: dict[str, Any], name: str = "axes.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def with_(**changes: Any) -> dict[str, Any]:
    """TWO_AXES with top-level sections replaced."""
    return {**TWO_AXES, **changes}


def refusal(path: Path, overrides: tuple[str, ...] = (), set_files: tuple[Path, ...] = ()) -> str:
    with pytest.raises(ConfigError) as info:
        load_axes(path, overrides, set_files)
    text = str(info.value)
    assert "\n" not in text and text.strip() == text, text
    return text


# -- what loads ----------------------------------------------------------------------------------


def test_two_axes_merge_the_top_level_under_each_axis(tmp_path: Path) -> None:
    axes = load_axes(write(tmp_path, TWO_AXES))
    assert axes.listed and axes.names == ("left", "right") and len(axes) == 2
    left, right = axes.axis("left").config, axes.axis("right").config
    assert (left.drive.node_id, right.drive.node_id) == (1, 2)
    assert left.design.force_gain == right.design.force_gain == 3.0        # the top level's
    assert (left.plant.inertia, right.plant.inertia) == (0.25, 0.3)         # the axis' own wins
    assert left.environment.stiffness == right.environment.stiffness == 500.0
    assert axes.period == 0.001
    assert axes.couplings == (Coupling("left", "right", 2000.0, 20.0),)
    assert axes.coupled("left") == axes.coupled("right") == axes.couplings


def test_set_reaches_one_axis_or_every_axis(tmp_path: Path) -> None:
    path = write(tmp_path, TWO_AXES)
    axes = load_axes(path, ["axes.left.plant.inertia=0.4", "plant.viscous_friction=0.01", "plant.inertia=0.2"])
    left, right = axes.axis("left").config, axes.axis("right").config
    assert left.plant.inertia == 0.4            # its own override
    assert right.plant.inertia == 0.3           # its own key beats a top-level --set
    assert left.plant.viscous_friction == right.plant.viscous_friction == 0.01


def test_a_set_file_may_name_an_axis_key(tmp_path: Path) -> None:
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text("axes.right.plant.inertia: 0.5\ndesign.force_gain: 4.0\n")
    axes = load_axes(write(tmp_path, TWO_AXES), (), (overlay,))
    assert axes.axis("right").config.plant.inertia == 0.5
    assert axes.axis("left").config.design.force_gain == 4.0
    # a relative reference.file is taken from the set file's directory, an axis' as the top level's
    (tmp_path / "sets").mkdir()
    (tmp_path / "sets" / "paths.yaml").write_text("axes.right.reference.file: r.csv\nreference.file: t.csv\n")
    axes = load_axes(write(tmp_path, TWO_AXES), (), (tmp_path / "sets" / "paths.yaml",))
    assert [axes.axis(n).config.reference.file for n in ("left", "right")] == [
        str(tmp_path / "sets" / "t.csv"), str(tmp_path / "sets" / "r.csv")]


def test_a_config_without_axes_is_the_one_axis_load_config_reads(tmp_path: Path) -> None:
    single = {"plant": {"inertia": 0.4}, "drive": {"node_id": 7}, "loop": {"period": 0.002}}
    path = write(tmp_path, single, "one.yaml")
    overrides = ("design.force_gain=1.5",)
    axes = load_axes(path, overrides)
    assert not axes.listed and axes.names == (SINGLE_AXIS,)
    assert axes.axes[0].config == load_config(path, overrides)
    assert not has_axes(path) and has_axes(write(tmp_path, TWO_AXES))
    assert load_axes("demo").axes[0].config == load_config("demo")   # a shipped config too


# -- what is refused: one line, the culprit and what is allowed ------------------------------------


def test_unknown_axis_in_set(tmp_path: Path) -> None:
    text = refusal(write(tmp_path, TWO_AXES), ("axes.middle.plant.inertia=0.3",))
    assert "'middle'" in text and "axes: left, right" in text


def test_axis_key_without_section(tmp_path: Path) -> None:
    text = refusal(write(tmp_path, TWO_AXES), ("axes.left.inertia=0.3",))
    assert "expected axes.NAME.section.key=value" in text


def test_axis_key_on_a_single_axis_config(tmp_path: Path) -> None:
    text = refusal(write(tmp_path, {"plant": {"inertia": 0.3}}), ("axes.left.plant.inertia=0.3",))
    assert "lists no axes" in text and "section.key" in text


def test_unknown_axis_in_a_set_file(tmp_path: Path) -> None:
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text("axes.middle.plant.inertia: 0.5\n")
    text = refusal(write(tmp_path, TWO_AXES), (), (overlay,))
    assert "--set-file" in text and "'middle'" in text and "axes: left, right" in text


@pytest.mark.parametrize("key", SHARED_LOOP_KEYS)
def test_shared_loop_key_in_an_axis(tmp_path: Path, key: str) -> None:
    section, name = key.split(".")
    data = with_(axes=[TWO_AXES["axes"][0], {**TWO_AXES["axes"][1], section: {name: 1}}])
    text = refusal(write(tmp_path, data))
    assert f"axis right: {key} is shared by every axis" in text and "set it at the top level" in text


def test_shared_loop_key_in_an_axis_override(tmp_path: Path) -> None:
    text = refusal(write(tmp_path, TWO_AXES), ("axes.left.loop.period=0.002",))
    assert "axis left: loop.period is shared" in text


def test_duplicate_names(tmp_path: Path) -> None:
    data = with_(axes=[TWO_AXES["axes"][0], {**TWO_AXES["axes"][1], "name": "left"}])
    text = refusal(write(tmp_path, data))
    assert "axes[1].name = 'left'" in text and "two axes have this name" in text


@pytest.mark.parametrize("name, says", [(None, "None"), ("", "''"), ("1st", "'1st'"), ("a.b", "'a.b'"),
                                        ("x" * 33, "x" * 10), ("my axis", "'my axis'"), (3, "3")])
def test_bad_names(tmp_path: Path, name: Any, says: str) -> None:
    entry = {"drive": {"node_id": 1}} if name is None else {"name": name, "drive": {"node_id": 1}}
    text = refusal(write(tmp_path, with_(axes=[entry])))
    assert "axes[0].name" in text and says in text and "letters, digits, _ or -" in text


@pytest.mark.parametrize("axes, says", [([], "non-empty list"), ("left", "non-empty list"),
                                        ({"left": {}}, "non-empty list"), (["left"], "expected a mapping"),
                                        ([{"name": "left", "plant": 3}], "is not a section")])
def test_bad_axes_lists(tmp_path: Path, axes: Any, says: str) -> None:
    assert says in refusal(write(tmp_path, with_(axes=axes)))


def test_a_bad_key_in_an_axis_names_the_axis(tmp_path: Path) -> None:
    data = with_(axes=[TWO_AXES["axes"][0], {**TWO_AXES["axes"][1], "plant": {"inertia": -1.0}}])
    text = refusal(write(tmp_path, data))
    assert text.startswith("axis right: ") and "plant.inertia" in text


def coupling(**entry: Any) -> dict[str, Any]:
    return with_(environment={"coupling": [{"axes": ["left", "right"], "stiffness": 1.0, **entry}]})


def test_coupling_to_a_missing_axis(tmp_path: Path) -> None:
    text = refusal(write(tmp_path, coupling(axes=["left", "middle"])))
    assert "couples axis 'middle'" in text and "axes: left, right" in text


def test_self_coupling(tmp_path: Path) -> None:
    text = refusal(write(tmp_path, coupling(axes=["left", "left"])))
    assert "couples axis 'left' to itself" in text and "joins two axes" in text


def test_coupled_twice(tmp_path: Path) -> None:
    data = with_(environment={"coupling": [{"axes": ["left", "right"]}, {"axes": ["right", "left"]}]})
    assert "coupled twice" in refusal(write(tmp_path, data))


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), "stiff", True, 1e11, None])
def test_bad_stiffness(tmp_path: Path, value: Any) -> None:
    text = refusal(write(tmp_path, coupling(stiffness=value)))
    assert "environment.coupling[0].stiffness" in text and "expected a finite number >= 0 and <= 1e10" in text


@pytest.mark.parametrize("entry, says", [({"axes": "left"}, "the names of two axes"),
                                         ({"axes": ["left"]}, "the names of two axes"),
                                         ({"spring": 3}, "unknown key 'spring'; allowed: axes, stiffness, damping"),
                                         ({"damping": -2}, "coupling[0].damping")])
def test_bad_coupling_entries(tmp_path: Path, entry: dict[str, Any], says: str) -> None:
    assert says in refusal(write(tmp_path, coupling(**entry)))


def test_coupling_without_axes(tmp_path: Path) -> None:
    data = {"environment": {"coupling": [{"axes": ["left", "right"], "stiffness": 1.0}]}}
    text = refusal(write(tmp_path, data))
    assert "lists no axes" in text and "axes: list" in text


# -- hypothesis: each axis is load_config of the merged keys -------------------------------------

#: keys an axis may set, with values their checks accept
AXIS_KEYS = {
    "plant.inertia": st.floats(0.01, 10.0), "plant.viscous_friction": st.floats(0.0, 5.0),
    "plant.coulomb_friction": st.floats(0.0, 1.0), "environment.stiffness": st.floats(0.0, 1e5),
    "environment.damping": st.floats(0.0, 100.0), "design.force_gain": st.floats(0.0, 10.0),
    "design.dob_bandwidth": st.floats(1.0, 2000.0), "reference.amplitude": st.floats(-5.0, 5.0),
    "reference.kind": st.sampled_from(["step", "sine", "chirp"]), "sensor.encoder_resolution": st.integers(0, 2**16),
    "drive.node_id": st.integers(-1, 63), "loop.torque_limit": st.floats(0.1, 50.0),
}
keys = st.dictionaries(st.sampled_from(sorted(AXIS_KEYS)), st.none(), max_size=5).flatmap(
    lambda chosen: st.fixed_dictionaries({k: AXIS_KEYS[k] for k in chosen}))
names = st.lists(st.from_regex(r"[A-Za-z][A-Za-z0-9_-]{0,8}", fullmatch=True), min_size=1, max_size=4, unique=True)


def nested(flat: dict[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for key, value in flat.items():
        section, name = key.split(".")
        out.setdefault(section, {})[name] = value
    return out


@BOUNDED
@given(top=keys, names=names, own=st.lists(keys, min_size=4, max_size=4), over=st.lists(keys, min_size=4, max_size=4),
       period=st.sampled_from([0.001, 0.002, 0.0005]))
def test_each_axis_is_load_config_of_its_merged_keys(tmp_path: Path, top: dict[str, Any], names: list[str],
                                                     own: list[dict[str, Any]], over: list[dict[str, Any]],
                                                     period: float) -> None:
    data = {**nested({"loop.period": period, **top}),
            "axes": [{"name": n, **nested(own[i])} for i, n in enumerate(names)]}
    overrides = [f"axes.{n}.{k}={v!r}" for i, n in enumerate(names) for k, v in over[i].items()]
    axes = load_axes(write(tmp_path, data), overrides)
    assert axes.names == tuple(names)
    for i, axis in enumerate(axes.axes):
        merged = {"loop.period": period, **top, **own[i], **over[i]}
        alone = write(tmp_path, nested(merged), "alone.yaml")
        assert axis.config == load_config(alone), axis.name
