"""``--vary KEY=DIST``: the parser (one-line ConfigError naming what is allowed for anything
else) and the draws (a run's values from SeedSequence(seed).spawn(n)[i] alone)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.config.schema import key_fields
from dobhil.campaign.draws import ALLOWED, Kind, Vary, child, draw, numeric_keys, parse_vary
from dobhil.errors import ConfigError

finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e12, max_value=1e12)


@given(st.sampled_from(["normal", "uniform", "loguniform"]), finite, finite)
@settings(max_examples=200, deadline=None)
def test_a_well_formed_dist_parses_or_says_what_is_wrong(kind: str, a: float, b: float) -> None:
    item = f"plant.inertia={kind}:{a!r}:{b!r}"
    valid = (b >= 0 if kind == "normal" else b > a) and (kind != "loguniform" or a > 0)
    # and the values it draws allowed for the key (a normal: its mean)
    meta = key_fields()["plant.inertia"].metadata
    lo, hi = (a, a) if kind == "normal" else (a, b)
    valid = valid and meta["minimum"] <= lo and hi <= meta["maximum"]
    if valid:
        v = parse_vary(item)
        assert (v.key, v.a, v.b, v.kind.name.lower()) == ("plant.inertia", a, b, kind)
        assert parse_vary(v.text()) == v   # what the summary writes reads back
    else:
        with pytest.raises(ConfigError) as err:
            parse_vary(item)
        assert "\n" not in str(err.value) and item in str(err.value)


@given(st.text(max_size=40))
@settings(max_examples=300, deadline=None)
def test_any_text_parses_or_is_one_config_error_line(text: str) -> None:
    for item in (text, f"plant.inertia={text}", f"{text}=uniform:0:1"):
        try:
            v = parse_vary(item)
        except ConfigError as exc:
            assert "\n" not in str(exc)
        else:
            assert isinstance(v, Vary) and math.isfinite(v.a) and math.isfinite(v.b)


@pytest.mark.parametrize(("item", "says"), [
    ("plant.inertai=normal:1:0.1", "unknown config key 'plant.inertai'; allowed: plant.inertia"),
    ("design.disturbance_model=uniform:0:1", "not a numeric config key"),
    ("plant.inertia=gauss:1:0.1", f"unknown distribution 'gauss'; allowed: {ALLOWED}"),
    ("plant.inertia=uniform:1:1", "an empty range"),
    ("plant.inertia=loguniform:0:1", "loguniform needs LO > 0"),
    ("plant.inertia=normal:1:-0.1", "standard deviation must be >= 0"),
    ("plant.inertia=normal:1", "expected two numbers MEAN:STD"),
    ("plant.inertia=uniform:a:b", "expected two numbers LO:HI"),
    ("plant.inertia=uniform:0:inf", "must be finite"),
    ("plant.inertia", "expected KEY=DIST"),
    ("sensor.seed=uniform:0:9", "set by the campaign"),
    # values the key does not allow: every run would fail alone, refused once instead
    ("plant.inertia=uniform:1e-13:2e-13", "plant.inertia = 1e-13: out of range; allowed: >= 1e-12"),
    ("plant.inertia=loguniform:0.1:1e7", "plant.inertia = 10000000.0: out of range"),
    ("environment.stiffness=normal:-5:1", "environment.stiffness: every value must be >= 0 (got -5)"),
    # numbers a lockstep run never reads: not called "not numeric", which reads as a typo
    ("loop.spin=uniform:0:1", "a key a lockstep emulated run never reads 'loop.spin'; allowed: plant.inertia"),
    ("drive.latency=uniform:0:1", "a key a lockstep emulated run never reads 'drive.latency'"),
])
def test_bad_vary_names_what_is_allowed(item: str, says: str) -> None:
    with pytest.raises(ConfigError, match=None) as err:
        parse_vary(item)
    assert says in str(err.value)


def test_the_draws_of_run_i_are_those_of_spawned_child_i() -> None:
    v = (parse_vary("plant.inertia=normal:0.25:0.02"), parse_vary("environment.stiffness=loguniform:1e3:1e5"))
    children = np.random.SeedSequence(11).spawn(6)
    for i, c in enumerate(children):
        rng = np.random.default_rng(c)
        expected = [rng.normal(0.25, 0.02), math.exp(rng.uniform(math.log(1e3), math.log(1e5)))]
        values, sensor_seed = draw(v, 11, i)
        assert list(values.values()) == expected
        assert sensor_seed == int(c.generate_state(1, np.uint32)[0])
        assert child(11, i).generate_state(4).tolist() == c.generate_state(4).tolist()
    assert draw(v, 11, 3) != draw(v, 12, 3) and draw(v, 11, 3) != draw(v, 11, 4)


def test_draws_respect_their_distribution() -> None:
    u = Vary("environment.damping", Kind.UNIFORM, 10.0, 20.0)
    lu = Vary("environment.stiffness", Kind.LOGUNIFORM, 1e3, 1e5)
    n = Vary("sensor.encoder_resolution", Kind.NORMAL, 4096.0, 100.0, integer=True)
    rows = [draw((u, lu, n), 5, i)[0] for i in range(400)]
    assert all(10 <= r["environment.damping"] < 20 and 1e3 <= r["environment.stiffness"] <= 1e5 for r in rows)
    logs = np.log10([r["environment.stiffness"] for r in rows])
    assert abs(np.median(logs) - 4.0) < 0.2        # log-uniform: the median at the geometric middle
    assert all(isinstance(r["sensor.encoder_resolution"], int) for r in rows)


def test_numeric_keys_are_numbers_only() -> None:
    keys = numeric_keys()
    assert "plant.inertia" in keys and "sensor.encoder_resolution" in keys
    assert "plant.disturbance" not in keys and "drive.profile" not in keys and "loop.spin" not in keys
