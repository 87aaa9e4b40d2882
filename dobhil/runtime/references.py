"""The interaction torque reference tau_int^ref(t) of a run (``reference.*`` keys).

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
- csv:    the file's ``time,tau_ref`` samples (absolute run time, ``start`` unused),
  linearly interpolated, the first value held before the first time and the last
  after the last, plus ``offset``.

``value(t)`` is scalar and cheap (the csv kind bisects a Python list).
"""

from __future__ import annotations

import bisect
import math
from enum import IntEnum
from pathlib import Path

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


class Reference:
    """A closed-form reference signal (every kind but csv)."""

    def __init__(self, kind: ReferenceKind, *, amplitude: float = 1.0, offset: float = 0.0,
                 start: float = 0.0, frequency: float = 1.0, frequency_end: float = 50.0,
                 ramp_time: float = 0.1, duration: float | None = None) -> None:
        self.kind = ReferenceKind(kind)
        self.amplitude = float(amplitude)
        self.offset = float(offset)
        self.start = float(start)
        self.frequency = float(frequency)
        self.frequency_end = float(frequency_end)
        self.ramp_time = float(ramp_time)
        self.duration = duration
        self._sweep = 0.0
        if self.kind is ReferenceKind.CHIRP:
            self._sweep = _sweep_time(duration, self.start)
        if self.kind is ReferenceKind.CSV:
            raise ValueError("use CsvReference for the csv kind")

    def value(self, t: float) -> float:
        """tau_int^ref at time ``t`` [s]."""
        tau = t - self.start
        if tau < 0.0:
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
                     ramp_time=config.ramp_time, duration=duration)


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
        out.append(x)
    return out[0], out[1]


def _sweep_time(duration: float | None, start: float) -> float:
    if duration is None:
        raise ConfigError("reference.kind chirp: the run duration is needed (loop.duration)")
    if not duration > start:
        raise ConfigError(f"reference.start: the chirp starts at {start} s, "
                          f"not before the end of the run ({duration} s)")
    return float(duration) - start
