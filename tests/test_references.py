"""Reference signals: each kind at literal times, csv parsing and its errors."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.config.schema import ReferenceConfig
from dobhil.errors import ConfigError
from dobhil.runtime.references import CsvReference, Reference, ReferenceKind, make_reference

R2 = math.sqrt(0.5)


def _ref(**kw: object) -> Reference:
    ref = make_reference(ReferenceConfig(**kw), duration=2.0)  # type: ignore[arg-type]
    assert isinstance(ref, Reference)
    return ref


def test_step() -> None:
    ref = _ref(kind="step", amplitude=3.0, offset=0.5, start=0.2)
    assert ref.kind is ReferenceKind.STEP
    assert [ref.value(t) for t in (0.0, 0.1999, 0.2, 5.0)] == [0.5, 0.5, 3.5, 3.5]


def test_ramp() -> None:
    ref = _ref(kind="ramp", amplitude=2.0, start=0.1, ramp_time=0.4)
    assert ref.value(0.05) == 0.0
    assert ref.value(0.1) == 0.0
    assert ref.value(0.3) == pytest.approx(1.0)
    assert ref.value(0.5) == 2.0 and ref.value(9.0) == 2.0


def test_sine() -> None:
    ref = _ref(kind="sine", amplitude=2.0, offset=1.0, frequency=5.0, start=0.1)
    assert ref.value(0.0) == 1.0
    assert ref.value(0.1) == 1.0
    assert ref.value(0.15) == pytest.approx(3.0)      # quarter period
    assert ref.value(0.25) == pytest.approx(-1.0)     # three quarters
    assert ref.value(0.3) == pytest.approx(1.0, abs=1e-12)


def test_chirp_sweeps_linearly_over_the_run() -> None:
    ref = _ref(kind="chirp", amplitude=1.0, frequency=1.0, frequency_end=3.0)
    # phase(t) = 2 pi (t + t^2 / 2) over T = 2 s
    assert ref.value(0.0) == 0.0
    assert ref.value(0.5) == pytest.approx(math.sin(2 * math.pi * 0.625))
    assert ref.value(0.5) == pytest.approx(-R2)
    assert ref.value(1.0) == pytest.approx(0.0, abs=1e-12)   # phase 3 pi
    # after the sweep it stays at 3 Hz, phase continuous: phase(2.25) = 2 pi (4 + 0.75)
    assert ref.value(2.25) == pytest.approx(-1.0)
    assert ref.value(2.0 - 1e-9) == pytest.approx(ref.value(2.0 + 1e-9), abs=1e-6)


def test_chirp_needs_a_duration_after_its_start() -> None:
    with pytest.raises(ConfigError, match="duration"):
        make_reference(ReferenceConfig(kind="chirp"))
    with pytest.raises(ConfigError, match="reference.start"):
        make_reference(ReferenceConfig(kind="chirp", start=3.0), duration=2.0)


def test_square() -> None:
    ref = _ref(kind="square", amplitude=2.0, offset=0.5, frequency=10.0, start=0.1)
    assert ref.value(0.05) == 0.5
    assert ref.value(0.1) == 2.5
    assert ref.value(0.14) == 2.5
    assert ref.value(0.16) == -1.5
    assert ref.value(0.21) == 2.5


def _write(tmp_path: Path, text: str, name: str = "ref.csv") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_csv_interpolates_and_holds(tmp_path: Path) -> None:
    _write(tmp_path, "time,tau_ref\n0.1,1.0\n0.3,3.0\n\n0.5, -1.0\n")
    ref = make_reference(ReferenceConfig(kind="csv", file="ref.csv", offset=0.5), tmp_path)
    assert isinstance(ref, CsvReference) and ref.kind is ReferenceKind.CSV
    assert ref.value(0.0) == 1.5
    assert ref.value(0.1) == 1.5
    assert ref.value(0.2) == pytest.approx(2.5)
    assert ref.value(0.3) == 3.5
    assert ref.value(0.45) == pytest.approx(0.5)
    assert ref.value(0.5) == -0.5 and ref.value(7.0) == -0.5


def test_csv_absolute_path_and_single_row(tmp_path: Path) -> None:
    path = _write(tmp_path, "time , tau_ref\n0.0,2.0\n")
    ref = make_reference(ReferenceConfig(kind="csv", file=str(path)), "/nonexistent")
    assert ref.value(-1.0) == 2.0 and ref.value(1.0) == 2.0


@pytest.mark.parametrize(("text", "message"), [
    ("", "empty file"),
    ("t,tau\n0,1\n", "line 1: expected the header 'time,tau_ref', got 't,tau'"),
    ("time,tau_ref\n", "no data rows"),
    ("time,tau_ref\n0,1\n0.1,abc\n", "line 3: tau_ref 'abc' is not a number"),
    ("time,tau_ref\n0,1\nx,2\n", "line 3: time 'x' is not a number"),
    ("time,tau_ref\n0,1\n0.1,2,3\n", "line 3: expected 2 columns"),
    ("time,tau_ref\n0,1\n0.2,2\n0.2,3\n", "line 4: time 0.2 does not increase"),
    ("time,tau_ref\n0,1\n0.1,nan\n", "line 3: tau_ref 'nan' is not finite"),
    ("time,tau_ref\n0,1e308\n1,0.2\n", "line 2: tau_ref '1e308' is outside the physical range"),
    ("time,tau_ref\n0,1\n2e15,0.2\n", "line 3: time '2e15' is outside the physical range"),
])
def test_csv_errors(tmp_path: Path, text: str, message: str) -> None:
    _write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        make_reference(ReferenceConfig(kind="csv", file="ref.csv"), tmp_path)
    assert "\n" not in str(info.value)


def test_csv_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        make_reference(ReferenceConfig(kind="csv", file="missing.csv"), tmp_path)
    with pytest.raises(ConfigError, match="needs a file"):
        make_reference(ReferenceConfig(kind="csv"), tmp_path)


def test_a_device_or_fifo_as_reference_file_is_refused_at_once(tmp_path: Path) -> None:
    """/dev/zero never ends and a FIFO blocks: both are refused before they are opened."""
    import os
    fifo = tmp_path / "ref.fifo"
    os.mkfifo(fifo)
    for name in ("/dev/zero", str(fifo), str(tmp_path)):
        with pytest.raises(ConfigError, match="not a regular file|is a directory"):
            make_reference(ReferenceConfig(kind="csv", file=name))


def test_a_relative_reference_file_is_taken_from_the_config_files_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """In a config file: from that file's directory; in --set: from the working directory."""
    from dobhil.cli.main import main
    from dobhil.config import load_config
    configs, elsewhere = tmp_path / "configs", tmp_path / "work"
    configs.mkdir()
    elsewhere.mkdir()
    (configs / "ref.csv").write_text("time,tau_ref\n0,0.5\n")
    (elsewhere / "other.csv").write_text("time,tau_ref\n0,0.25\n")
    demo = (Path(__file__).resolve().parents[1] / "configs" / "demo.yaml").read_text()
    config_file = configs / "csv.yaml"
    config_file.write_text(demo.replace("reference:\n  kind: step", "reference:\n  kind: csv\n  file: ref.csv"))
    monkeypatch.chdir(elsewhere)
    config = load_config(config_file)
    assert config.reference.file == "ref.csv"
    assert make_reference(config.reference, config_file.parent).value(1.0) == pytest.approx(0.5 + 0.2)
    overridden = load_config(config_file, ["reference.file=other.csv"])
    assert overridden.reference.file == str(elsewhere / "other.csv")
    assert make_reference(overridden.reference, config_file.parent).value(1.0) == pytest.approx(0.25 + 0.2)
    run = ["run", str(config_file), "--emulate", "--lockstep", "--duration", "0.05"]
    assert main(run) == 0
    assert main([*run, "--set", "reference.file=other.csv"]) == 0
    assert main(["run", "demo", "--emulate", "--lockstep", "--duration", "0.05", "--set", "reference.kind=csv",
                 "--set", "reference.file=other.csv"]) == 0  # a shipped config: still the working directory


# -- prbs and multisine (identification excitation) ----------------------------------

def _samples(ref: Reference, period: float, n: int) -> list[float]:
    return [ref.value(k * period) for k in range(n)]


def test_prbs_levels_are_offset_plus_minus_amplitude_held_for_a_clock_period() -> None:
    ref = _ref(kind="prbs", amplitude=0.5, offset=0.25, clock_period=0.004, seed=7, start=0.1)
    assert ref.value(0.0) == 0.25 and ref.value(0.0999) == 0.25     # before start: offset
    t = [0.1 + 1e-3 * k for k in range(1900)]
    v = [ref.value(x) for x in t]
    assert set(v) == {0.75, -0.25}
    clocks = [int((x - 0.1) // 0.004) for x in t]
    for k in range(1, len(t)):   # a level changes only where a new clock period begins
        if v[k] != v[k - 1]:
            assert clocks[k] != clocks[k - 1]
    assert ref.value(2.0) == 0.25 and ref.value(5.0) == 0.25      # after the run: offset


def test_prbs_is_its_seed_and_nothing_else() -> None:
    a = _samples(_ref(kind="prbs", seed=3, clock_period=1e-3), 1e-3, 1999)
    assert a == _samples(_ref(kind="prbs", seed=3, clock_period=1e-3), 1e-3, 1999)
    b = _samples(_ref(kind="prbs", seed=4, clock_period=1e-3), 1e-3, 1999)
    assert sum(x != y for x, y in zip(a, b)) > 500   # another seed: about half the levels differ
    # fair bits: the mean of 1999 +-1 levels is within 4 standard deviations of 0
    assert abs(sum(a)) < 4 * math.sqrt(len(a))


def test_prbs_levels_are_independent_of_each_other() -> None:
    """Level k is the same whether or not the ones before it were computed (counter-based),
    and consecutive levels are uncorrelated: the lag-1 autocorrelation of 20000 fair
    independent +-1 levels has standard deviation 1/sqrt(20000)."""
    from dobhil.runtime.references import prbs_bit
    bits = [1.0 if prbs_bit(11, k) else -1.0 for k in range(20000)]
    assert prbs_bit(11, 12345) == (bits[12345] > 0)
    lag1 = sum(x * y for x, y in zip(bits, bits[1:])) / (len(bits) - 1)
    assert abs(lag1) < 4 / math.sqrt(len(bits))


def test_prbs_lasts_its_duration() -> None:
    ref = _ref(kind="prbs", amplitude=1.0, offset=0.5, start=0.2, duration=0.5)
    assert {ref.value(0.2 + 1e-3 * k) for k in range(500)} == {1.5, -0.5}
    assert ref.value(0.701) == 0.5 and ref.value(1.9) == 0.5


@pytest.mark.parametrize("phases", ["schroeder", "random"])
def test_multisine_spectrum_has_exactly_its_lines(phases: str) -> None:
    """20 lines from 2 to 40 Hz (2 Hz apart), sampled 1 s at 1 kHz: numpy's FFT has power
    at those 20 bins and nowhere else (each line on a bin: no leakage)."""
    np = pytest.importorskip("numpy")
    ref = _ref(kind="multisine", amplitude=1.5, frequency=2.0, frequency_end=40.0, lines=20,
               phases=phases, seed=5)
    x = np.array(_samples(ref, 1e-3, 1000))
    spectrum = np.abs(np.fft.rfft(x)) / len(x)
    lines = set(range(2, 41, 2))
    on = np.array([spectrum[k] for k in sorted(lines)])
    off = np.array([spectrum[k] for k in range(len(spectrum)) if k not in lines])
    assert np.all(on > 1e-3) and np.max(off) < 1e-9 * np.max(on)
    assert np.allclose(on, on[0], rtol=1e-9)                 # equal amplitudes: a flat band
    assert 1.5 * (1 - 2e-3) < np.max(np.abs(x)) <= 1.5 * (1 + 1e-9)  # amplitude is the peak


def test_multisine_schroeder_phases_and_crest_factor() -> None:
    from dobhil.runtime.references import multisine_phases
    n = 8
    assert multisine_phases(n, "schroeder", 0) == [-math.pi * i * (i - 1) / n for i in range(1, 9)]
    schroeder = _ref(kind="multisine", frequency=1.0, frequency_end=30.0, lines=30)
    rand = Reference(ReferenceKind.MULTISINE, frequency=1.0, frequency_end=30.0, lines=30,
                     duration=2.0, phases="random", seed=0)
    # equal phases would give the worst crest factor sqrt(2 N) ~ 7.7, one sine sqrt(2);
    # Schroeder's phases come close to the sine, random ones do not
    assert math.sqrt(2.0) < schroeder.crest_factor < 2.0 < rand.crest_factor < math.sqrt(60.0)


def test_random_phases_are_their_seed() -> None:
    a = _samples(_ref(kind="multisine", phases="random", seed=1), 1e-3, 500)
    assert a == _samples(_ref(kind="multisine", phases="random", seed=1), 1e-3, 500)
    assert a != _samples(_ref(kind="multisine", phases="random", seed=2), 1e-3, 500)


def test_one_line_multisine_is_a_cosine() -> None:
    ref = _ref(kind="multisine", amplitude=2.0, offset=1.0, frequency=5.0, lines=1)
    for t in (0.0, 0.013, 0.1, 0.77):
        assert ref.value(t) == pytest.approx(1.0 + 2.0 * math.cos(2 * math.pi * 5.0 * t), abs=1e-12)


def test_multisine_band_must_be_a_band() -> None:
    with pytest.raises(ConfigError, match="frequency_end.*band") as info:
        _ref(kind="multisine", frequency=10.0, frequency_end=10.0, lines=5)
    assert "\n" not in str(info.value)


@settings(max_examples=25, deadline=None)
@given(lines=st.integers(1, 60), f_lo=st.floats(0.1, 50.0), width=st.floats(0.1, 200.0),
       phases=st.sampled_from(["schroeder", "random"]), seed=st.integers(0, 2**32),
       amplitude=st.floats(0.01, 10.0), offset=st.floats(-5.0, 5.0))
def test_multisine_never_exceeds_its_amplitude(lines: int, f_lo: float, width: float, phases: str,
                                               seed: int, amplitude: float, offset: float) -> None:
    """Sampled 20 times per period of its highest line, no value of a multisine is further
    from the offset than its amplitude (the peak search is refined, not just a grid)."""
    ref = _ref(kind="multisine", lines=lines, frequency=f_lo, frequency_end=f_lo + width,
               phases=phases, seed=seed, amplitude=amplitude, offset=offset)
    step = 1.0 / (20.0 * (f_lo + width))
    dev = [abs(ref.value(k * step) - offset) for k in range(int(2.0 / step))]
    assert max(dev) <= amplitude * (1 + 1e-9) + 1e-12


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**64 - 1), amplitude=st.floats(-10.0, 10.0), offset=st.floats(-5.0, 5.0),
       clock=st.floats(1e-4, 0.5), t=st.floats(0.0, 1.999))
def test_prbs_is_always_one_of_its_two_levels(seed: int, amplitude: float, offset: float,
                                              clock: float, t: float) -> None:
    ref = _ref(kind="prbs", seed=seed, amplitude=amplitude, offset=offset, clock_period=clock)
    assert ref.value(t) in (offset + amplitude, offset - amplitude)
