from __future__ import annotations

from pathlib import Path

import pytest

from dobhil.config import Config, load_config, to_yaml
from dobhil.config.axes import load_axes
from dobhil.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_config_doc_is_generated_from_the_key_table() -> None:
    import importlib.util
    spec = importlib.util.spec_from_file_location("gen", ROOT / "tools" / "gen_config_doc.py")
    mod = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    assert (ROOT / "docs" / "config.md").read_text() == mod.render()


def test_every_shipped_config_loads() -> None:
    """Each file, and each axis of a file that lists axes (a complete single-axis Config);
    a file without axes is its one axis."""
    listed = 0
    for path in sorted((ROOT / "configs").rglob("*.yaml")):
        axes = load_axes(path)
        assert all(isinstance(axis.config, Config) for axis in axes.axes)
        if axes.listed:
            listed += 1
            assert len(axes.axes) >= 2 and all(axes.axis(c.a) and axes.axis(c.b) for c in axes.couplings)
        else:
            assert axes.axes[0].config == load_config(path)
    assert listed >= 1   # configs/two-axis-demo.yaml


def test_resolved_yaml_round_trips(tmp_path: Path) -> None:
    cfg = load_config(ROOT / "configs/paper/fig2c.yaml", ["loop.period=5e-4"])
    out = tmp_path / "c.yaml"
    out.write_text(to_yaml(cfg))
    assert load_config(out) == cfg


@pytest.mark.parametrize("text,message", [
    ("[1, 2]", "expected a mapping"),
    ("plant: {inertia: 0}", "plant.inertia = 0.0: must be > 0"),
    ("loop: {position_min: 1, position_max: 0}", "must be below"),
    ("design: {delay_samples: -1}", "must be >= 0"),
])
def test_bad_files(tmp_path: Path, text: str, message: str) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(".", r"\.")):
        load_config(p)


def test_a_key_set_twice_takes_the_last_value() -> None:
    """As the README says: a repeated ``--set`` is not an error; the last one wins, as
    command-line options do (a key twice in one YAML mapping is an error: test_bad_files)."""
    first = load_config("demo", ["loop.period=0.002", "loop.period=0.0005"])
    second = load_config("demo", ["loop.period=0.0005", "loop.period=0.002"])
    assert (first.loop.period, second.loop.period) == (0.0005, 0.002)
