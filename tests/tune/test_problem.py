"""The robust set and the search's inputs, as tune builds them."""

from __future__ import annotations

import numpy as np
import pytest

from dobhil.config import load_config
from dobhil.tune.problem import (DECISION_KEYS, Margins, default_bounds, parse_bounds, parse_margins,
                                 parse_range, parse_uncertainty, robust_set)


def test_a_wide_range_is_log_spaced_and_a_narrow_one_linear() -> None:
    np.testing.assert_allclose(parse_range("environment.stiffness=1e3:1e5").values(3), [1e3, 1e4, 1e5])
    np.testing.assert_allclose(parse_range("environment.damping=10:50").values(3), [10.0, 30.0, 50.0])


def test_the_set_is_the_ranges_times_the_box_ends_and_centre() -> None:
    config = load_config("paper/fig3")   # plant.inertia 0.25
    box = robust_set(config, [parse_range("environment.stiffness=1e3:1e5")],
                     [parse_uncertainty("plant.inertia=±20%")], 4)
    assert box.size == 12 and box.keys == ("environment.stiffness", "plant.inertia")
    assert sorted(set(np.round(box.points["plant.inertia"], 12))) == [0.2, 0.25, 0.3]
    more = box.extended({"environment.stiffness": np.array([1e3, 5e3]), "plant.inertia": np.array([0.2, 0.2])})
    assert more.size == 13                     # (1e3, 0.2) was there already


@pytest.mark.parametrize("text", ["±20%", "+-20%", "+/-20 %", "20%"])
def test_uncertainty_spellings(text: str) -> None:
    assert parse_uncertainty(f"plant.inertia={text}").fraction == pytest.approx(0.2)


def test_margins_default_and_override() -> None:
    assert parse_margins([]) == Margins(gm_db=6.0, pm_deg=30.0, ms_db=6.0, overshoot_pct=20.0, noise=None)
    assert parse_margins(["gm=10,pm=45", "noise=0.02"]) == Margins(10.0, 45.0, 6.0, 20.0, 0.02)


def test_default_bounds_follow_the_config_and_period() -> None:
    config = load_config("paper/fig3", ["loop.period=0.0005", "design.force_gain=0"])
    bounds = default_bounds(config)
    assert bounds.lo["design.dob_bandwidth"] == pytest.approx(20.0)
    assert bounds.hi["design.rtob_bandwidth"] == pytest.approx(3000.0)
    assert (bounds.lo["design.force_gain"], bounds.hi["design.force_gain"]) == (0.05, 20.0)
    over = parse_bounds(config, ["design.force_gain=0.5:3"])
    assert (over.lo["design.force_gain"], over.hi["design.force_gain"]) == (0.5, 3.0)
    assert len(over.log10()) == len(DECISION_KEYS)
