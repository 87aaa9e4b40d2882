"""Axes coupled by a spring and damper, each stepped by its own emulated drive.

A coupling between axes ``a`` and ``b`` (:class:`dobhil.config.axes.Coupling`) pushes ``a``
with ``tau_c = K (q_b - q_a) + D (dq_b - dq_a)`` and ``b`` with ``-tau_c``, on the true
positions and velocities, on top of each plant's own environment: two actuators pressing on
each other, or a master/slave pair joined by a compliant link. :func:`couple_plants` gives
each axis the object its emulated drive steps (:class:`CoupledPlant`, the
:class:`~dobhil.emulator.plant.Plant` surface); an axis without a coupling keeps its plain
:class:`~dobhil.emulator.plant.Plant`, untouched.

The scheme. The drives step one after another (:class:`dobhil.drives.emulated.LockstepBus`
advances each emulator in turn, the real-time emulator process likewise), and each may cut
its step at the instant a command latches, so the axes never take one joint step of the
stacked system. Instead, for each piece ``[t, t + h]`` an axis steps:

- its own part of the coupling, ``-K q_a - D dq_a``, is integrated *exactly*, inside the
  plant's own ZOH matrices (:meth:`Plant.couple`): a stiff spring cannot make the step
  unstable, and the contact modes, friction and sub-steps work as for any plant;
- the partner's part, ``K q_b + D dq_b``, is held over the piece at its value at the
  piece's *middle* ``t + h/2`` (the midpoint rule): taken from the partner's recorded
  trajectory when the partner has passed that instant (a cubic Hermite interpolation of
  its states at its own step boundaries: position error O(h^4), velocity O(h^3)), else
  extrapolated from its newest state with the acceleration of its last piece (position
  error O(h^3), velocity O(h^2)).

The midpoint value of a smooth input held over ``h`` makes a local error O(h^3), so the
scheme is second order: the global error over a fixed time is O(h^2) (measured, with the
stacked linear system integrated by scipy as the reference: tests/emulator/test_coupling.py).
What no scheme that steps one axis before the other can know is a torque step of the
partner inside the coming piece (its command has not reached its plant yet): extrapolating
across it, the leading axis' estimate of the partner's velocity is off by
``dU h / (2 J_b)`` for that one piece, a local error ``D dU h^2 / (2 J_a J_b)`` in the
leading axis' velocity (and ``K dU h^3 / (8 J_a J_b)``), so piecewise-constant torques
that jump by ``dU`` every step make the damper's share first order in ``h``, with that
small constant; a spring alone stays second order.

Reported torques: :attr:`CoupledPlant.coupling_torque` (``tau_c`` on this axis) and
:attr:`CoupledPlant.interaction_torque` (the environment's plus ``-tau_c``: what a force
sensor between the axes reads, pushing positive, as for the environment) use the partner's
state at this axis' own time -- exact when both stand at the same instant, where the two
axes' coupling torques are equal and opposite.

Stability: the plant's own part is exact, the partner's is explicit, so a stiff enough
coupling makes the step unstable. With ``omega = sqrt(K (1/J_a + 1/J_b))`` the energy of two
free servos joined by an undamped spring decays (the scheme's own damping, a damping ratio
of 8e-4 at ``omega dt = 0.4``) up to ``omega dt = 2.2`` for equal inertias and for an
inertia ratio of 100 either way; at 2.4 the ratio-100 pair with the heavy axis stepped first
grows (``python tools/coupling_error.py``). :func:`step_limit` is the step at
``omega dt = 2`` for the stiffest coupling: a run's period must stay below it.

A plant with backlash cannot be coupled (its load is massless); :func:`couple_plants`
refuses it, as it refuses a coupling to an axis not in the mapping.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dobhil.config.axes import Coupling
from dobhil.drives.emulated import PlantLike
from dobhil.emulator.plant import Plant, PlantTruth

__all__ = ["SAME_INSTANT", "STABLE_OMEGA_DT", "CoupledPlant", "Link", "couple_plants", "step_limit"]

#: trajectory points an axis keeps for its partners (a partner lags by at most a step)
_TRACK = 8
#: omega dt up to which the scheme is stable with a margin (measured stable up to 2.2)
STABLE_OMEGA_DT = 2.0
#: [s] two axes' times this close are one instant: each axis' time is its own sum of step
#: lengths, and two sums of the same steps cut differently differ in the last bits
SAME_INSTANT = 1e-9


@dataclass(frozen=True)
class Link:
    """One coupling as one axis sees it: the partner, the spring and the damper."""

    partner: CoupledPlant
    stiffness: float
    damping: float


class _Track:
    """The newest true states ``(t, q, dq)`` of an axis at its step boundaries."""

    def __init__(self) -> None:
        self.points: deque[tuple[float, float, float]] = deque(maxlen=_TRACK)

    def add(self, t: float, q: float, dq: float) -> None:
        points = self.points
        if points and t <= points[-1][0]:
            points.clear()   # time went back (a reset): the past no longer holds
        points.append((t, q, dq))

    def at(self, t: float) -> tuple[float, float]:
        """Position and velocity at ``t``: interpolated inside the record, extrapolated past
        its end with the last piece's acceleration (module docstring)."""
        points = self.points
        t1, q1, v1 = points[-1]
        if t >= t1 or len(points) == 1:
            tau = t - t1
            acc = _slope(points[-2], points[-1]) if len(points) > 1 else 0.0
            return q1 + tau * (v1 + 0.5 * tau * acc), v1 + tau * acc
        for i in range(len(points) - 1, 0, -1):
            if points[i - 1][0] <= t:
                return _hermite(points[i - 1], points[i], t)
        return points[0][1], points[0][2]   # older than the record: the oldest state


def _slope(p0: tuple[float, float, float], p1: tuple[float, float, float]) -> float:
    return (p1[2] - p0[2]) / (p1[0] - p0[0])


def _hermite(p0: tuple[float, float, float], p1: tuple[float, float, float],
             t: float) -> tuple[float, float]:
    """The cubic through both ends' positions and velocities, and its slope, at ``t``."""
    t0, q0, v0 = p0
    t1, q1, v1 = p1
    h = t1 - t0
    s = (t - t0) / h
    s2, s3 = s * s, s * s * s
    q = ((2 * s3 - 3 * s2 + 1) * q0 + (s3 - 2 * s2 + s) * h * v0
         + (-2 * s3 + 3 * s2) * q1 + (s3 - s2) * h * v1)
    v = ((6 * s2 - 6 * s) * (q0 - q1) / h + (3 * s2 - 4 * s + 1) * v0 + (3 * s2 - 2 * s) * v1)
    return q, v


class CoupledPlant:
    """One axis of a coupled set: its :class:`Plant`, coupled to its partners (module
    docstring). Reads like the plant (parameters fall through to it); step it through this
    object only."""

    position: float  # measured position [rad] (the plant's sensor)
    velocity: float  # measured velocity [rad/s]

    def __init__(self, name: str, plant: Plant) -> None:
        self.name = name
        self._plant = plant
        self._links: list[Link] = []
        self.track = _Track()
        self._sync()

    # -- set-up ---------------------------------------------------------------

    def link(self, partner: CoupledPlant, stiffness: float, damping: float) -> None:
        """Add a coupling to ``partner``; the plant's own part grows by this one's."""
        self._links.append(Link(partner, stiffness, damping))
        self._plant.couple(sum(k.stiffness for k in self._links), sum(k.damping for k in self._links))

    @property
    def links(self) -> tuple[Link, ...]:
        return tuple(self._links)

    @property
    def plant(self) -> Plant:
        """The plant this axis steps (coupled in place)."""
        return self._plant

    # -- the PlantLike surface --------------------------------------------------

    def step(self, torque_nm: float, dt: float) -> None:
        """Advance ``dt`` s with the motor torque held; the partners' part of the coupling
        held at its value at the middle of the step."""
        plant = self._plant
        middle = plant.time + 0.5 * dt
        total = 0.0
        for link in self._links:
            q, dq = link.partner.state_at(middle)
            total += link.stiffness * q + link.damping * dq
        plant.coupling_input = total
        plant.step(torque_nm, dt)
        self._sync()

    def prepare(self, dt: float) -> None:
        self._plant.prepare(dt)

    def state_at(self, t: float) -> tuple[float, float]:
        """This axis' true position and velocity at ``t`` (exact at its own time)."""
        plant = self._plant
        if abs(t - plant.time) <= SAME_INSTANT:
            return plant.true_position, plant.true_velocity
        return self.track.at(t)

    def reset(self) -> None:
        self._plant.reset()
        self.track.points.clear()
        self._sync()

    def set_state(self, position: float, velocity: float) -> None:
        self._plant.set_state(position, velocity)
        self.track.points.clear()
        self._sync()

    def _sync(self) -> None:
        plant = self._plant
        self.position, self.velocity = plant.position, plant.velocity
        self.track.add(plant.time, plant.true_position, plant.true_velocity)

    # -- what the drives and sessions read ---------------------------------------

    @property
    def coupling_torque(self) -> float:
        """``sum_j K (q_j - q) + D (dq_j - dq)``: the couplings' torque on this axis now,
        the partners taken at this axis' time."""
        plant = self._plant
        q, dq, t = plant.true_position, plant.true_velocity, plant.time
        total = 0.0
        for link in self._links:
            qj, dqj = link.partner.state_at(t)
            total += link.stiffness * (qj - q) + link.damping * (dqj - dq)
        return total

    @property
    def interaction_torque(self) -> float:
        """The environment's interaction torque plus the couplings' reaction, ``-tau_c``."""
        return self._plant.interaction_torque - self.coupling_torque

    @property
    def time(self) -> float:
        return self._plant.time

    @property
    def true_position(self) -> float:
        return self._plant.true_position

    @property
    def true_velocity(self) -> float:
        return self._plant.true_velocity

    @property
    def load_position(self) -> float:
        return self._plant.load_position

    @property
    def in_contact(self) -> bool:
        return self._plant.in_contact

    @property
    def motor_torque(self) -> float:
        return self._plant.motor_torque

    @property
    def friction_torque(self) -> float:
        return self._plant.friction_torque

    @property
    def disturbance_torque(self) -> float:
        return self._plant.disturbance_torque

    def truth(self) -> PlantTruth:
        plant = self._plant
        return PlantTruth(q=plant.true_position, dq=plant.true_velocity, tau_motor=plant.motor_torque,
                          tau_int=self.interaction_torque, t=plant.time)

    def __getattr__(self, name: str) -> Any:
        # the plant's parameters and helpers (inertia, stiffness, matrices ...); only called
        # for names this class does not define
        if name.startswith("__") or name == "_plant":
            raise AttributeError(name)
        return getattr(self._plant, name)


def couple_plants(plants: Mapping[str, Plant], couplings: Sequence[Coupling]) -> dict[str, PlantLike]:
    """The object each axis' emulated drive steps: a :class:`CoupledPlant` for an axis with a
    coupling of nonzero stiffness or damping (its plant coupled in place), the plant itself
    otherwise. ValueError naming the coupling when it names an axis not in ``plants``, or
    an axis whose plant has backlash."""
    out: dict[str, PlantLike] = dict(plants)
    coupled: dict[str, CoupledPlant] = {}
    for c in couplings:
        for name in (c.a, c.b):
            if name not in plants:
                raise ValueError(f"coupling {c.a}-{c.b}: no axis {name!r}; axes: {', '.join(plants)}")
        if c.a == c.b:
            raise ValueError(f"coupling {c.a}-{c.b}: couples an axis to itself")
        if not (c.stiffness or c.damping):
            continue
        for name in (c.a, c.b):
            if plants[name].backlash:
                raise ValueError(f"coupling {c.a}-{c.b}: axis {name} has plant.backlash > 0; "
                                 "a coupled axis has none")
            if name not in coupled:
                coupled[name] = CoupledPlant(name, plants[name])
        coupled[c.a].link(coupled[c.b], c.stiffness, c.damping)
        coupled[c.b].link(coupled[c.a], c.stiffness, c.damping)
    out.update(coupled)
    return out


def step_limit(inertias: Mapping[str, float], couplings: Sequence[Coupling]) -> float:
    """[s] the longest step the scheme is stable at for these couplings (module docstring):
    ``STABLE_OMEGA_DT / omega`` of the stiffest, ``omega = sqrt(K (1/J_a + 1/J_b))``; inf
    without a spring. ``inertias``: each axis' ``plant.inertia`` by name."""
    limit = math.inf
    for c in couplings:
        if c.stiffness > 0.0:
            omega = math.sqrt(c.stiffness * (1.0 / inertias[c.a] + 1.0 / inertias[c.b]))
            limit = min(limit, STABLE_OMEGA_DT / omega)
    return limit
