"""The interaction torque reference tau_int^ref(t) of a run (``reference.*`` keys; with
``loop.mode: torque`` it is the torque command itself).

Every signal is ``offset`` before ``start`` and ``offset + s(t - start)`` after,
with ``A = amplitude``, ``f = frequency`` [Hz], ``tau = t - start``:

- step:   ``s = A``
- ramp:   ``s = A min(tau / ramp_time, 1)`` (0 at start, A after ramp_time)
- sine:   ``s = A sin(2 pi f tau)``
- chirp:  ``s = A sin(phi(tau))``, a linear sweep from ``f`` to ``frequency_end`` over
  the rest of the run, ``T = duration - start``:
  ``phi = 2 pi (f tau + (f_end - f) tau^2 / (2 T))``; after T it stays at f_end
  (phase continuous). The run duration is given at construction.
- square: ``s = +A`` for the first half of each period ``1/f``, ``-A`` for the second.
- prbs:   ``s = +-A``, a pseudo-random binary sequence: level ``k`` (held for
  ``clock_period``, ``k = floor(tau / clock_period)``) is ``+A`` or ``-A`` by one bit of
  ``splitmix64(seed, k)`` -- fair independent bits, so its power is flat up to about
  ``0.44 / clock_period`` (sinc^2, first zero at ``1 / clock_period``). Not an
  m-sequence: any length and any seed, O(1) per sample with no table.
- multisine: ``s = g sum_i cos(2 pi f_i tau + phi_i)``, ``N = lines`` lines evenly spaced
  from ``f_lo = frequency`` to ``f_hi = frequency_end`` (one line: ``f_lo``), phases
  Schroeder's ``phi_i = -pi i (i - 1) / N`` (low crest factor) or uniform random from
  ``seed``; ``g`` scales the peak over the excitation to ``A`` (found on a grid of 64
  points per period of ``f_hi``, refined by Newton's method: see :func:`_multisine_peak`).
  :attr:`Reference.crest_factor` is peak / RMS.

prbs and multisine last ``duration`` after ``start`` (0: to the end of the run) and
are ``offset`` after it.
 ``time,tau_ref`` samples (absolute run time, ``start`` unused),
  linearly interpolated, the first value held before the first time and the last
  after the last, plus ``offset``.

``value(t)`` is scalar and cheap (the csv kind bisects a Python list; a multisine takes one
``math.cos`` per line: about 6 us for 40 lines, measured on a busy 2-core machine, next to
the controller's 0.3 us, so keep ``lines`` to tens at 1 kHz).
"""

from __future__ import annotations

import bisect
import math
from enum import IntEnum
from pathlib import Path

from dobhil.config.load import MAX_MAGNITUDE
from dobhil.config.schema import ReferenceConfig
from dobhil.config.yamlio import TextFileError, read_text_file
from dobhil.errors import ConfigError

__all__ = ["CsvReference", "Reference", "ReferenceKind", "make_reference", "read_csv"]

CSV_HEADER: tuple[str, str] = ("time", "tau_ref")
#: the largest reference file read (hours of samples at 1 kHz; a larger file is not one)
CSV_MAX_BYTES = 256 << 20


class ReferenceKind(IntEnum):
    STEP = 0
    RAMP = 1
    SINE = 2
    CHIRP = 3
    SQUARE = 4
    CSV = 5
    PRBS = 6
    MULTISINE = 7


#: multisine peak search: grid points per period of the highest line, and at most this many
MULTISINE_GRID = 64
MULTISINE_GRID_MAX = 1 << 22
#: multisine peak refinement: Newton steps from this many of the grid's largest local maxima
MULTISINE_REFINE = 16
MULTISINE_NEWTON = 6


class Reference:
    """A closed-form reference signal (every kind but csv)."""

    def __init__(self, kind: ReferenceKind, *, amplitude: float = 1.0, offset: float = 0.0,
                 start: float = 0.0, frequency: float = 1.0, frequency_end: float = 50.0,
                 ramp_time: float = 0.1, duration: float | None = None,
                 clock_period: float = 2e-3, lines: int = 20, phases: str = "schroeder",
                 seed: int = 0, length: float = 0.0) -> None:
        self.kind = ReferenceKind(kind)
        self.amplitude = float(amplitude)
        self.offset = float(offset)
        self.start = float(start)
        self.frequency = float(frequency)
        self.frequency_end = float(frequency_end)
        self.ramp_time = float(ramp_time)
        self.duration = duration
        self.clock_period = float(clock_period)
        self.seed = int(seed)
        self._sweep = 0.0
        #: how long a prbs or multisine lasts after start (inf: to the end of the run)
        self.length = (_excitation_length(length, duration, self.start)
                       if self.kind in (ReferenceKind.PRBS, ReferenceKind.MULTISINE) else math.inf)
        self._lines: tuple[tuple[float, float], ...] = ()   # multisine (2 pi f_i, phi_i)
        self._gain = 0.0
        self._level: tuple[int, bool] = (-1, False)   # prbs: the last clock index and its bit
        self.crest_factor = math.nan
        if self.kind is ReferenceKind.CHIRP:
            self._sweep = _sweep_time(duration, self.start)
        if self.kind is ReferenceKind.CSV:
            raise ValueError("use CsvReference for the csv kind")
        if self.kind is ReferenceKind.MULTISINE:
            self._multisine(int(lines), phases)

    def _multisine(self, lines: int, phases: str) -> None:
        freqs = multisine_frequencies(self.frequency, self.frequency_end, lines)
        phis = multisine_phases(lines, phases, self.seed)
        self._lines = tuple((2.0 * math.pi * f, p) for f, p in zip(freqs, phis))
        peak = _multisine_peak(freqs, phis, self.length)
        self._gain = self.amplitude / peak
        self.crest_factor = peak / math.sqrt(0.5 * lines)

    def value(self, t: float) -> float:
        """tau_int^ref at time ``t`` [s]."""
        tau = t - self.start
        if tau < 0.0 or tau >= self.length:
            return self.offset
        return self.offset + self._shape(tau)

    __call__ = value

    def _shape(self, tau: float) -> float:
        kind, a = self.kind, self.amplitude
        if kind is ReferenceKind.STEP:
            return a
        if kind is ReferenceKind.RAMP:
            return a * min(tau / self.ramp_time, 1.0)
        if kind is ReferenceKind.SINE:
            return a * math.sin(2.0 * math.pi * self.frequency * tau)
        if kind is ReferenceKind.CHIRP:
            return a * math.sin(self._chirp_phase(tau))
        if kind is ReferenceKind.PRBS:
            k = int(tau // self.clock_period)
            if k != self._level[0]:   # a new clock period: hash once, hold it (a pure cache)
                self._level = (k, prbs_bit(self.seed, k))
            return a if self._level[1] else -a
        if kind is ReferenceKind.MULTISINE:
            return self._gain * sum(math.cos(w * tau + p) for w, p in self._lines)
        return a if (tau * self.frequency) % 1.0 < 0.5 else -a  # SQUARE

    def _chirp_phase(self, tau: float) -> float:
        f0, f1, sweep = self.frequency, self.frequency_end, self._sweep
        if tau <= sweep:
            return 2.0 * math.pi * (f0 * tau + 0.5 * (f1 - f0) * tau * tau / sweep)
        return 2.0 * math.pi * (0.5 * (f0 + f1) * sweep + f1 * (tau - sweep))


class CsvReference:
    """Samples ``(time, tau_ref)`` from a file, linearly interpolated, ends held."""

    kind = ReferenceKind.CSV

    def __init__(self, times: list[float], values: list[float], *, offset: float = 0.0) -> None:
        if not times or len(times) != len(values):
            raise ValueError("CsvReference needs as many values as times, at least one")
        self.times = [float(t) for t in times]
        self.values = [float(v) for v in values]
        self.offset = float(offset)

    @classmethod
    def from_file(cls, path: str | Path, *, offset: float = 0.0) -> CsvReference:
        times, values = read_csv(path)
        return cls(times, values, offset=offset)

    def value(self, t: float) -> float:
        """tau_int^ref at time ``t`` [s]."""
        ts, vs = self.times, self.values
        i = bisect.bisect_right(ts, t)
        if i == 0:
            return self.offset + vs[0]
        if i == len(ts):
            return self.offset + vs[-1]
        t0, t1 = ts[i - 1], ts[i]
        v0, v1 = vs[i - 1], vs[i]
        return self.offset + v0 + (v1 - v0) * (t - t0) / (t1 - t0)

    __call__ = value


def make_reference(config: ReferenceConfig, base_dir: str | Path | None = None, *,
                   duration: float | None = None) -> Reference | CsvReference:
    """The reference of ``config``; a relative csv ``file`` is taken from ``base_dir``
    (the directory of the config file naming it; default: the working directory; a
    ``--set`` override is made absolute by :func:`dobhil.config.load_config`);
    ``duration`` (the run's, ``loop.duration``) is needed by the chirp."""
    kind = ReferenceKind[config.kind.upper()]
    if kind is ReferenceKind.CSV:
        if not config.file:
            raise ConfigError("reference.file: the csv reference needs a file")
        path = Path(config.file)
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        return CsvReference.from_file(path, offset=config.offset)
    return Reference(kind, amplitude=config.amplitude, offset=config.offset, start=config.start,
                     frequency=config.frequency, frequency_end=config.frequency_end,
                     ramp_time=config.ramp_time, duration=duration,
                     clock_period=config.clock_period, lines=config.lines, phases=config.phases,
                     seed=config.seed, length=config.duration)


def read_csv(path: str | Path) -> tuple[list[float], list[float]]:
    """``(times, values)`` of a ``time,tau_ref`` CSV file; ConfigError (one line) if bad."""
    p = Path(path)
    try:  # a regular file of bounded size: /dev/zero or a FIFO would never end
        text = read_text_file(p, limit=CSV_MAX_BYTES).removeprefix("\ufeff")
    except FileNotFoundError:
        raise ConfigError(f"reference file {p} does not exist") from None
    except TextFileError as exc:
        raise ConfigError(f"reference file {p} {exc}") from None
    lines = text.splitlines()
    if not lines:
        raise ConfigError(f"{p}: empty file, expected the header 'time,tau_ref'")
    if tuple(c.strip() for c in lines[0].split(",")) != CSV_HEADER:
        raise ConfigError(f"{p}: line 1: expected the header 'time,tau_ref', "
                          f"got {lines[0].strip()!r}")
    times: list[float] = []
    values: list[float] = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        t, v = _parse_row(p, number, line)
        if times and not t > times[-1]:
            raise ConfigError(f"{p}: line {number}: time {t!r} does not increase "
                              f"(previous {times[-1]!r})")
        times.append(t)
        values.append(v)
    if not times:
        raise ConfigError(f"{p}: no data rows after the header")
    return times, values


def _parse_row(path: Path, number: int, line: str) -> tuple[float, float]:
    cells = [c.strip() for c in line.split(",")]
    if len(cells) != 2:
        raise ConfigError(f"{path}: line {number}: expected 2 columns (time,tau_ref), "
                          f"got {len(cells)}")
    out: list[float] = []
    for name, cell in zip(CSV_HEADER, cells):
        try:
            x = float(cell)
        except ValueError:
            raise ConfigError(f"{path}: line {number}: {name} {cell!r} is not a number") from None
        if not math.isfinite(x):
            raise ConfigError(f"{path}: line {number}: {name} {cell!r} is not finite")
        if abs(x) > MAX_MAGNITUDE:   # the bound every config number has: larger is a typo
            raise ConfigError(f"{path}: line {number}: {name} {cell!r} is outside the physical range; "
                              f"allowed: |value| <= {MAX_MAGNITUDE:g} (SI units)")
        out.append(x)
    return out[0], out[1]


def _sweep_time(duration: float | None, start: float) -> float:
    if duration is None:
        raise ConfigError("reference.kind chirp: the run duration is needed (loop.duration)")
    if not duration > start:
        raise ConfigError(f"reference.start: the chirp starts at {start} s, "
                          f"not before the end of the run ({duration} s)")
    return float(duration) - start


_MASK64 = (1 << 64) - 1


def splitmix64(x: int) -> int:
    """Sebastiano Vigna's splitmix64 finaliser of ``x`` (a 64-bit integer hash): every
    output bit depends on every input bit; pure integers, so the same on every machine."""
    z = (x + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def prbs_bit(seed: int, k: int) -> bool:
    """Level ``k`` of the prbs of ``seed``: the top bit of ``splitmix64`` of the seed's
    hash plus ``k`` (a counter-based generator: any level without the ones before it)."""
    return bool(splitmix64((splitmix64(seed) + k) & _MASK64) >> 63)


def multisine_frequencies(f_lo: float, f_hi: float, lines: int) -> list[float]:
    """``lines`` frequencies evenly spaced from ``f_lo`` to ``f_hi`` (one line: ``f_lo``)."""
    if lines < 1:
        raise ConfigError(f"reference.lines = {lines}: must be >= 1")
    if lines == 1:
        return [float(f_lo)]
    if not f_hi > f_lo:
        raise ConfigError(f"reference.frequency_end = {f_hi!r}: the multisine band must end "
                          f"above reference.frequency = {f_lo!r} (or reference.lines = 1)")
    step = (f_hi - f_lo) / (lines - 1)
    return [f_lo + i * step for i in range(lines)]


def multisine_phases(lines: int, phases: str, seed: int) -> list[float]:
    """Schroeder's ``-pi i (i - 1) / N`` (i = 1..N) or uniform in [0, 2 pi) from ``seed``."""
    if phases == "schroeder":
        return [-math.pi * i * (i - 1) / lines for i in range(1, lines + 1)]
    if phases == "random":
        import numpy as np
        return [float(p) for p in np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, lines)]
    raise ConfigError(f"reference.phases = {phases!r}: allowed: schroeder, random")


def _multisine_peak(freqs: list[float], phis: list[float], length: float) -> float:
    """max |sum cos(2 pi f_i tau + phi_i)| over the excitation, or over one common period
    when the lines share one (``1 / spacing``) and it is shorter: the largest of a grid of
    MULTISINE_GRID points per period of the highest line (at most MULTISINE_GRID_MAX points,
    then the first part of the excitation), refined by Newton's method on the derivative
    at the MULTISINE_REFINE largest local maxima of the grid. Why refine: between grid
    points the sum can rise by up to (pi / grid)^2 / 2 times the sum of the line amplitudes,
    which for many lines is several per cent of the peak; Newton's steps from the nearest
    grid point reach the maximum itself."""
    import numpy as np
    span = length
    if len(freqs) > 1:
        spacing = freqs[1] - freqs[0]
        if abs(freqs[0] / spacing - round(freqs[0] / spacing)) < 1e-9:
            span = min(span, 1.0 / spacing)   # periodic: one period has every value
    else:
        span = min(span, 1.0 / freqs[0])
    cap = MULTISINE_GRID_MAX / (max(freqs) * MULTISINE_GRID)
    span = cap if not span > 0.0 else min(span, cap)   # also: no excitation or no known end
    n = int(min(MULTISINE_GRID_MAX, max(3.0, math.ceil(span * max(freqs) * MULTISINE_GRID))))
    w = 2.0 * math.pi * np.asarray(freqs, dtype=float)
    p = np.asarray(phis, dtype=float)
    tau = np.linspace(0.0, span, n, endpoint=False)
    total = np.zeros(n)
    for wi, pi in zip(w, p):
        total += np.cos(wi * tau + pi)
    mag = np.abs(total)
    local = np.flatnonzero((mag >= np.roll(mag, 1)) & (mag >= np.roll(mag, -1)))
    best = local[np.argsort(mag[local])[-MULTISINE_REFINE:]]
    x = tau[best]
    for _ in range(MULTISINE_NEWTON):   # extrema of the sum: zeros of its derivative
        arg = np.outer(x, w) + p
        d1 = -(np.sin(arg) * w).sum(axis=1)
        d2 = -(np.cos(arg) * w * w).sum(axis=1)
        ok = d2 != 0.0
        x = np.where(ok, x - np.divide(d1, d2, out=np.zeros_like(d1), where=ok), x)
    refined = np.abs(np.cos(np.outer(x, w) + p).sum(axis=1))
    return float(max(mag.max(), refined.max()))


def _excitation_length(length: float, duration: float | None, start: float) -> float:
    """How long a prbs or multisine lasts (``reference.duration``; 0: to the end of the run,
    ``duration``; inf when neither is known)."""
    if length > 0.0:
        return float(length)
    if duration is None:
        return math.inf
    return max(float(duration) - start, 0.0)
