"""The box certificates (dobhil/analysis/certify.py, certify_sampled.py) against independent
evidence: the loop's determinant (the affinity the edge theorem needs), eigenvalue scans of
the box, a bisection for a one-key box's exact end, and python-control's disk margins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dobhil.analysis import interval_expm as iv
from dobhil.analysis.certify import (Box, Verdict, box_from_specs, certify_continuous, closed_loop,
                                     params_at, parse_range)
from dobhil.analysis.certify_sampled import certify_sampled, lyapunov_closes, plant_enclosure
from dobhil.analysis.disk_margin import disk_margin
from dobhil.config import load_config
from dobhil.errors import ConfigError
from dobhil.synthesis.loop import loop, sampled_plant

#: the design dobhil tune chose for Fig. 3 over K 1e3..1e5, D 10..200 (docs/tune.md)
TUNED = ["design.dob_bandwidth=40.6673", "design.rtob_bandwidth=29.2889",
         "design.identified_inertia=0.125154", "design.force_gain=0.623056"]
KEYS = ("environment.stiffness", "environment.damping", "plant.inertia", "plant.viscous_friction")


def fig3(*sets: str) -> object:
    return load_config("paper/fig3", list(sets))


def test_the_loop_polynomial_times_j_is_affine_in_all_four_keys_jointly() -> None:
    """J det(sI - A(p)) at the middle of two random points is the mean of its values there, at
    complex s: the premise of the edge theorem, checked on the loop's own matrices."""
    config = fig3()
    rng = np.random.default_rng(3)
    s = np.array([1j * 50.0, -3.0 + 400j, 20.0 + 2000j])
    for _ in range(10):
        p0 = dict(zip(KEYS, (rng.uniform(1e3, 1e5), rng.uniform(0, 300), rng.uniform(0.1, 1), rng.uniform(0, 1))))
        p1 = dict(zip(KEYS, (rng.uniform(1e3, 1e5), rng.uniform(0, 300), rng.uniform(0.1, 1), rng.uniform(0, 1))))
        mid = {k: 0.5 * (p0[k] + p1[k]) for k in KEYS}
        f = [_scaled_det(config, p, s) for p in (p0, p1, mid)]
        assert np.allclose(f[2], 0.5 * (f[0] + f[1]), rtol=1e-7, atol=0), (p0, p1)
        # and not affine without the factor J (the reason the polynomial is scaled)
        f_raw = [x / p["plant.inertia"] for x, p in zip(f, (p0, p1, mid))]
        assert not np.allclose(f_raw[2], 0.5 * (f_raw[0] + f_raw[1]), rtol=1e-4, atol=0)


def _scaled_det(config: object, point: dict[str, float], s: np.ndarray) -> np.ndarray:
    a = closed_loop(config, point, sampled=False)  # type: ignore[arg-type]
    return np.array([point["plant.inertia"] * np.linalg.det(x * np.eye(a.shape[0]) - a) for x in s])


def _max_re(config: object, points: dict[str, np.ndarray]) -> np.ndarray:
    return np.max(np.linalg.eigvals(closed_loop(config, points, sampled=False)).real, axis=-1)  # type: ignore[arg-type]


def test_a_one_key_box_ends_where_the_loop_loses_stability() -> None:
    """At D = 10 the paper's gains lose stability at one stiffness K* (found here by bisecting
    the eigenvalues): [1e3, K*(1 - 1e-6)] is certified, [1e3, K*(1 + 1e-6)] refuted with a
    point beyond K*."""
    config = fig3("environment.damping=10")
    lo, hi = 1e3, 1e5
    assert _max_re(config, {"environment.stiffness": np.array([lo])})[0] < 0
    assert _max_re(config, {"environment.stiffness": np.array([hi])})[0] > 0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if _max_re(config, {"environment.stiffness": np.array([mid])})[0] < 0:
            lo = mid
        else:
            hi = mid
    k_star = 0.5 * (lo + hi)
    inside = certify_continuous(config, Box(("environment.stiffness",), (1e3,), (k_star * (1 - 1e-6),)))
    assert inside.verdict is Verdict.CERTIFIED
    beyond = certify_continuous(config, Box(("environment.stiffness",), (1e3,), (k_star * (1 + 1e-6),)))
    assert beyond.verdict is Verdict.REFUTED and beyond.point is not None
    assert beyond.point["environment.stiffness"] > k_star
    assert beyond.spectral_abscissa is not None and beyond.spectral_abscissa > 0
    assert beyond.boundaries[0]["environment.stiffness"] == pytest.approx(k_star, rel=1e-7)


def test_fig3_paper_gains_are_refuted_and_the_tuned_design_certified() -> None:
    box = box_from_specs(["environment.stiffness=1e3:1e5", "environment.damping=10:200"])
    paper = certify_continuous(fig3(), box)
    assert paper.verdict is Verdict.REFUTED and paper.point is not None
    assert _max_re(fig3(), {k: np.array([v]) for k, v in paper.point.items()})[0] > 0
    tuned = certify_continuous(fig3(*TUNED), box)
    assert tuned.verdict is Verdict.CERTIFIED and tuned.gain_margin is not None
    # the gain margin over the box: C_f times it is unstable at its worst point, just below it is not
    gm = tuned.gain_margin
    worst = {k: np.array([v]) for k, v in gm.up_at.items()}
    cf = 0.623056
    above = fig3(*TUNED, f"design.force_gain={cf * gm.up * (1 + 1e-4)}")
    below = fig3(*TUNED, f"design.force_gain={cf * gm.up * (1 - 1e-4)}")
    assert _max_re(above, worst)[0] > 0 > _max_re(below, worst)[0]
    # and no point of a grid has a smaller stable C_f factor
    scan = _scan_points(box, 12)
    above_all = fig3(*TUNED, f"design.force_gain={cf * gm.up * (1 - 1e-4)}")
    assert np.all(_max_re(above_all, scan) < 0)


def _scan_points(box: Box, n: int) -> dict[str, np.ndarray]:
    axes = [np.geomspace(lo, hi, n) if lo > 0 and hi / lo >= 4 else np.linspace(lo, hi, n)
            for lo, hi in zip(box.lo, box.hi)]
    mesh = np.meshgrid(*axes, indexing="ij")
    return {k: m.ravel() for k, m in zip(box.keys, mesh)}


def _random_case(rng: np.random.Generator) -> tuple[object, Box]:
    """A design near the paper's or the tuned one, and a box of 1 to 3 keys."""
    base = TUNED if rng.random() < 0.4 else []
    cf = (0.623056 * rng.uniform(1.0, 12.0)) if base else 2.0 * rng.uniform(0.5, 2.0)
    # the keys outside the box at a stiff, lightly damped environment: near the paper gains' edge
    config = fig3(*base, f"design.force_gain={cf}", "environment.stiffness=2e4", "environment.damping=12")
    keys = list(rng.choice(KEYS, size=int(rng.integers(1, 4)), replace=False))
    ranges = {"environment.stiffness": (1e3, 2e5), "environment.damping": (1.0, 150.0),
              "plant.inertia": (0.1, 0.6), "plant.viscous_friction": (0.0, 2.0)}
    lo, hi = [], []
    for k in keys:
        a, b = sorted(rng.uniform(*ranges[k], size=2))
        lo.append(a)
        hi.append(b)
    return config, Box(tuple(keys), tuple(lo), tuple(hi))


def test_a_dense_scan_never_contradicts_the_continuous_certificate() -> None:
    """20 seeded boxes: a certified box has no unstable point on a dense grid, a box with one
    is refuted, and every refuting point is unstable by its eigenvalues. Both answers occur."""
    rng = np.random.default_rng(11)
    seen = {Verdict.CERTIFIED: 0, Verdict.REFUTED: 0}
    for _ in range(20):
        config, box = _random_case(rng)
        answer = certify_continuous(config, box, gain_margin=False)
        scan_unstable = bool(np.any(_max_re(config, _scan_points(box, 30 if len(box.keys) < 3 else 10)) >= 0))
        seen[answer.verdict] += 1
        if answer.verdict is Verdict.CERTIFIED:
            assert not scan_unstable, box
        else:
            assert answer.point is not None
            assert _max_re(config, {k: np.array([v]) for k, v in answer.point.items()})[0] > 0, box
        if scan_unstable:
            assert answer.verdict is Verdict.REFUTED, box
    assert seen[Verdict.CERTIFIED] >= 3 and seen[Verdict.REFUTED] >= 3, seen


def _rho(config: object, points: dict[str, np.ndarray]) -> np.ndarray:
    return np.max(np.abs(np.linalg.eigvals(closed_loop(config, points, sampled=True))), axis=-1)  # type: ignore[arg-type]


def test_a_dense_scan_never_contradicts_the_sampled_certificate() -> None:
    """The same on the sampled loop (small boxes, so some close within the budget): certified
    means no scanned point with spectral radius >= 1; a scan that finds one means refuted."""
    rng = np.random.default_rng(5)
    seen = {v: 0 for v in Verdict}
    for _ in range(20):
        config, box = _random_case(rng)
        # shrink the box around its centre: the sampled bound closes on small boxes
        c = box.centre()
        width = rng.choice([0.02, 0.2, 1.0])
        box = Box(box.keys, tuple(c[k] - width * (c[k] - lo) for k, lo in zip(box.keys, box.lo)),
                  tuple(c[k] + width * (hi - c[k]) for k, hi in zip(box.keys, box.hi)))
        answer = certify_sampled(config, box, refinements=3000)
        scan_unstable = bool(np.any(_rho(config, _scan_points(box, 12 if len(box.keys) < 3 else 6)) >= 1.0))
        seen[answer.verdict] += 1
        if answer.verdict is Verdict.CERTIFIED:
            assert not scan_unstable, box
        if answer.verdict is Verdict.REFUTED:
            assert answer.point is not None
            assert _rho(config, {k: np.array([v]) for k, v in answer.point.items()})[0] >= 1.0
        if scan_unstable:
            assert answer.verdict is Verdict.REFUTED, box
    assert seen[Verdict.CERTIFIED] >= 3 and seen[Verdict.REFUTED] >= 3, seen


@pytest.mark.parametrize("input_delay", [0.0, 0.0004])
def test_the_plant_enclosure_holds_the_runtimes_sampled_plant(input_delay: float) -> None:
    """Random points of a sub-box: sampled_plant (the runtime's) lies inside the enclosure;
    and the enclosure is tight (its radius shrinks with the box)."""
    config = fig3(f"design.input_delay={input_delay}")
    rng = np.random.default_rng(7)
    lo = {"environment.stiffness": 2e3, "environment.damping": 20.0, "plant.inertia": 0.2}
    hi = {"environment.stiffness": 2.5e3, "environment.damping": 40.0, "plant.inertia": 0.3}
    enclosure = plant_enclosure(config, lo, hi)
    for _ in range(50):
        p = {k: float(rng.uniform(lo[k], hi[k])) for k in lo}
        for box_m, m in zip(enclosure, sampled_plant(params_at(config, p))):
            assert box_m.contains(m), p
    small = plant_enclosure(config, lo, {k: lo[k] * (1 + 1e-6) for k in lo})
    assert small[0].rad.max() < 1e-4 * enclosure[0].rad.max()


def test_interval_expm_encloses_the_exponential_of_every_member() -> None:
    import scipy.linalg
    rng = np.random.default_rng(2)
    mid = rng.normal(size=(3, 3)) * 3
    rad = np.abs(rng.normal(size=(3, 3))) * 0.01
    enclosure = iv.expm(iv.IMat(mid, rad))
    for _ in range(100):
        x = mid + rad * rng.uniform(-1, 1, size=(3, 3))
        assert enclosure.contains(scipy.linalg.expm(x))
    assert enclosure.rad.max() < 0.05 * np.abs(enclosure.mid).max()   # and not vacuous


def test_the_sampled_certificate_refutes_fig3_and_decides_a_small_box() -> None:
    box = box_from_specs(["environment.stiffness=1e3:1e5", "environment.damping=10:200"])
    paper = certify_sampled(fig3(), box, refinements=10)
    assert paper.verdict is Verdict.REFUTED and paper.spectral_radius is not None and paper.spectral_radius >= 1
    small = box_from_specs(["environment.stiffness=2e4:2.1e4", "environment.damping=100:101"])
    assert certify_sampled(fig3(*TUNED), small, refinements=200).verdict is Verdict.CERTIFIED


def test_disk_margin_matches_python_control() -> None:
    control = pytest.importorskip("control")
    if not hasattr(control, "disk_margins"):
        pytest.skip("this python-control has no disk_margins")
    config = fig3(*TUNED)
    params = params_at(config, {"environment.stiffness": 3e4, "environment.damping": 30.0})
    for period in (None, 0.001):
        a, b, c, _ = loop(params, sampled=period is not None, force_gain=0.0).siso("tau_per", "tau_int_hat")
        ours = disk_margin(a, b, c, 0.623056, period=period)
        sys_ = control.ss(a, b, c, 0, period or 0) * 0.623056
        top = math.pi / period if period else 1e5
        alpha, gm_db, pm = control.disk_margins(sys_, np.geomspace(1e-2, top, 40000))
        assert ours.alpha == pytest.approx(float(alpha), rel=1e-4)
        assert ours.gain_db == pytest.approx(float(gm_db), rel=1e-3)
        assert ours.phase_deg == pytest.approx(float(pm), rel=1e-3)


@pytest.mark.parametrize("spec, words", [
    ("design.force_gain=1:2", "treats only environment.stiffness, environment.damping, plant.inertia"),
    ("environment.stiffness=5:1", "LO < HI"),
    ("environment.stiffness=3:3", "LO < HI"),
    ("environment.stiffness=a:3", "two finite numbers"),
    ("environment.stiffness=1:inf", "two finite numbers"),
    ("environment.stiffness", "two finite numbers"),
    ("plant.inertia=0:1", "must be > 0"),
    ("environment.damping=-1:1", "must be >= 0"),
])
def test_bad_ranges_are_one_line(spec: str, words: str) -> None:
    with pytest.raises(ConfigError, match=words.replace(".", r"\.")) as err:
        parse_range(spec)
    assert "\n" not in str(err.value)


def test_the_lyapunov_bound_never_closes_on_an_interval_with_an_unstable_member() -> None:
    """Seeded interval matrices A_m +- R: where the bound closes, no member tried (random ones and
    sign corners A_m +- R) has spectral radius >= 1; where a member is unstable, it does not close.
    Both outcomes occur, and one case is built to hold an unstable member (A_m + R itself)."""
    rng = np.random.default_rng(9)
    outcomes = {True: 0, False: 0}
    for _ in range(200):
        n = int(rng.integers(2, 7))
        a = rng.normal(size=(n, n))
        a *= rng.uniform(0.3, 0.97) / np.max(np.abs(np.linalg.eigvals(a)))
        r = np.abs(rng.normal(size=(n, n))) * 10.0 ** rng.uniform(-4, -0.5)
        closes = bool(lyapunov_closes(iv.IMat(a, r)))
        members = [a + r * rng.choice([-1.0, 1.0], size=(n, n)) for _ in range(100)]
        members += [a + r * rng.uniform(-1, 1, size=(n, n)) for _ in range(100)]
        unstable = any(np.max(np.abs(np.linalg.eigvals(m))) >= 1.0 for m in members)
        outcomes[closes] += 1
        assert not (closes and unstable)
    assert outcomes[True] >= 20 and outcomes[False] >= 20, outcomes
    built = np.diag([0.9, 0.5, -0.3])
    assert np.max(np.abs(np.linalg.eigvals(built + 0.15 * np.eye(3)))) >= 1.0
    assert not lyapunov_closes(iv.IMat(built, 0.15 * np.eye(3)))
    assert lyapunov_closes(iv.IMat(built, 0.01 * np.eye(3)))


def test_a_pole_within_the_resolution_of_the_axis_refutes_nothing() -> None:
    """K_env from 1e-5 N m/rad (D_env 50): the position's pole is at s = -K/D = -2e-7 1/s,
    left of the axis but inside the analysis' tolerance of it. That was "refuted at
    environment.stiffness=1e-05 (max Re(s) = -2e-07 1/s)": a refutation with no eigenvalue
    right of the axis. Neither shown stable nor unstable, it is undecided, named there."""
    from dobhil.cli.certify_cmd import _continuous, _continuous_text
    cert = certify_continuous(fig3(), Box(("environment.stiffness",), (1e-5,), (1e3,)))
    assert cert.verdict is Verdict.UNDECIDED
    assert cert.point == {"environment.stiffness": 1e-5}
    assert cert.spectral_abscissa is not None and cert.spectral_abscissa < 0
    text = _continuous_text(_continuous(cert))
    assert text.startswith("undecided at environment.stiffness=1e-05 (max Re(s) = -2e-07 1/s") and "refuted" not in text


@pytest.mark.parametrize("sampled", [False, True])
def test_the_disk_margin_of_such_a_point_is_not_called_unstable(sampled: bool) -> None:
    """The same point: the certificate says undecided, so its disk-margin line must not say
    "the loop is unstable there" (it did); a clearly unstable point still does."""
    from dobhil.cli.certify_cmd import _disk, text_lines
    box = Box(("environment.stiffness",), (1e-5,), (1e3,))
    soft = _disk(fig3(), box, sampled, {"environment.stiffness": 1e-5}, [])
    stiff = _disk(fig3(), box, sampled, {"environment.stiffness": 1e5, "environment.damping": 10.0}, [])
    assert not soft["stable"] and soft["unresolved"] and not stiff["stable"] and not stiff["unresolved"]
    lines = text_lines({"box": {"environment.stiffness": (1e-5, 1e3)}, "disk_margin": {"d": soft, "e": stiff}})
    assert "neither stable nor unstable" in lines[1] and "unstable there" not in lines[1], lines
    assert lines[2].endswith("the loop is unstable there"), lines


def test_an_enclosure_too_wide_to_stay_finite_does_not_close_and_the_box_is_undecided() -> None:
    """A box within the keys' ranges whose interval exponential overflows (friction 0..1e7 on
    the demo: entries up to 4e7 1/s over a period) does not close, so the budget ends
    undecided; numpy's SVD failed on its infinite radius, and certify said it "cannot answer
    this box ... check that it is within the keys' ranges", which it is."""
    stable = np.array([[0.5, 0.0], [0.0, 0.5]])
    wide = iv.IMat(np.stack([stable, stable]), np.stack([np.zeros((2, 2)), np.full((2, 2), np.inf)]))
    assert lyapunov_closes(wide).tolist() == [True, False]
    cert = certify_sampled(load_config("demo"), box_from_specs(["plant.viscous_friction=0:1e7"]), refinements=4)
    assert cert.verdict is Verdict.UNDECIDED
