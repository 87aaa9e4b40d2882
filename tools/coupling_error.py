"""The coupled-plant figures of docs/ecosystem.md: error against the stacked system, the
scheme's own damping and where it goes unstable.

    python tools/coupling_error.py

The error table uses the reference of ``tests/emulator/test_coupling.py`` (the stacked
continuous system integrated by ``scipy.linalg.expm``, two servos, one in contact with its
environment, a coupling spring and damper, the same piecewise-constant torques): the largest
position and velocity error over 0.2 s per step ``h``. Then two free 0.25 kg m^2 servos
joined by an undamped 2e4 N m/rad spring at 1 ms: the energy left after 2 s, and the
largest energy over 3 s (relative to the start) at growing ``omega dt``,
``omega = sqrt(K (1/J_a + 1/J_b))``.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np

from dobhil.config.axes import Coupling
from dobhil.emulator.coupling import couple_plants
from dobhil.emulator.plant import Plant

TEST = Path(__file__).resolve().parents[1] / "tests" / "emulator" / "test_coupling.py"


def _reference_module() -> object:
    spec = importlib.util.spec_from_file_location("coupling_reference", TEST)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def energy_run(ja: float, jb: float, k: float, seconds: float, dt: float = 1e-3) -> tuple[float, float]:
    """(energy at the end, largest energy) over ``seconds``, relative to the start."""
    pa, pb = Plant(inertia=ja, initial_position=0.01), Plant(inertia=jb)
    plants = couple_plants({"a": pa, "b": pb}, [Coupling("a", "b", k, 0.0)])

    def energy() -> float:
        return 0.5 * (ja * pa.true_velocity ** 2 + jb * pb.true_velocity ** 2) + \
            0.5 * k * (pa.true_position - pb.true_position) ** 2

    start, peak = energy(), 0.0
    for _ in range(round(seconds / dt)):
        plants["a"].step(0.0, dt)
        plants["b"].step(0.0, dt)
        e = energy() / start
        if not math.isfinite(e) or e > 1e6:
            return math.inf, math.inf
        peak = max(peak, e)
    return energy() / start, peak


def main() -> None:
    ref = _reference_module()
    cases = [("K 2e4, D 0, smooth torques", 2e4, 0.0, ref.smooth),   # type: ignore[attr-defined]
             ("K 2e4, D 20, smooth torques", 2e4, 20.0, ref.smooth),   # type: ignore[attr-defined]
             ("K 2e4, D 20, torque steps every 2 ms", 2e4, 20.0, ref.jumps(3))]   # type: ignore[attr-defined]
    print("case | h [ms] | max position error [rad] | max velocity error [rad/s]")
    for name, k, d, torque in cases:
        for h in (2e-3, 1e-3, 5e-4, 2.5e-4):
            err = np.abs(ref.emulated(h, k, d, torque) - ref.reference(h, k, d, torque)).max(axis=0)   # type: ignore[attr-defined]
            print(f"{name} | {h * 1e3:g} | {max(err[0], err[2]):.2e} | {max(err[1], err[3]):.2e}")
    left, _ = energy_run(0.25, 0.25, 2e4, 2.0)
    zeta = -math.log(left) / (2.0 * math.sqrt(2e4 * 8.0) * 2.0)
    print(f"undamped K 2e4, J 0.25 + 0.25, 1 ms: energy after 2 s {left:.3f} of the start "
          f"(a numerical damping ratio of {zeta:.1e})")
    print("J_a J_b K | omega dt | largest energy over 3 s | energy at 3 s")
    for ja, jb, k in ((0.25, 0.25, 2e4), (0.25, 0.25, 1e5), (0.25, 0.25, 4e5), (0.25, 0.25, 8e5),
                      (0.01, 1.0, 2e4), (1.0, 0.01, 2e4), (1.0, 0.01, 5e4)):
        w = math.sqrt(k * (1 / ja + 1 / jb)) * 1e-3
        end, peak = energy_run(ja, jb, k, 3.0)
        print(f"{ja:g} {jb:g} {k:g} | {w:.2f} | {peak:.3g} | {end:.3g}")


if __name__ == "__main__":
    main()
