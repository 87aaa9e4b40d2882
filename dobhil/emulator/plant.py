"""The exact servo and its environment, integrated for the emulator.

The linear part is the analysis' model itself, not a copy of its equations:
:func:`dobhil.synthesis.models.plant_matrices` (in contact) and
:func:`dobhil.synthesis.models.servo_matrices` (free motion), discretised with
:func:`dobhil.synthesis.controller.discretize` (zero-order hold, exact for an input
held constant). With ``x = [q, dq]`` and ``e = q - q_c`` (``q_c`` the contact
position)::

    contact (e >= 0):  x' = A_env x + B (u - tau_d^u - tau_c),  tau_int = K e + D dq
    free    (e <  0):  x' = A_srv x + B (u - tau_d^u - tau_c),  tau_int = 0

``plant_matrices`` puts the environment's rest position at 0; the emulator keeps
its state *relative to the contact position* (``e`` instead of ``q``), which is
the exact change of variables (the free servo does not depend on ``q`` at all, so
the same ``e`` serves both modes) and is better conditioned than adding
``K q_c`` as a constant input. With ``q_c = 0`` the relative state is ``q``
itself, bit for bit.

The contact is linear while ``e >= 0``: the damper may pull (``tau_int < 0``
while the servo retracts inside the environment). Clipping the force at 0 would
be more physical but would make the emulator differ from the analysis model even
when the servo starts in contact; keeping it linear makes the emulator *exactly*
the analysed plant whenever it stays in contact, and the contact opens only when
the position leaves the environment.

Nonlinear parts are sub-stepped (``substeps`` per call, each with the input held):

- the mode (contact or free) is taken at the start of each sub-step; a contact
  transition is therefore placed with an error of at most one sub-step;
- Coulomb friction ``tau_c = F_c sign(dq)`` with a Karnopp stiction band: when
  ``|dq| <= v_s`` and the rest of the torque acting at zero velocity,
  ``u - tau_d^u - K e`` (``K e`` in contact only), is within ``+-F_c`` the servo
  sticks for the sub-step (``dq = 0``, ``q`` kept); inside the band but with a
  larger torque, friction opposes that torque. ``v_s`` defaults to
  ``2 F_c h / J`` (twice the velocity Coulomb friction alone removes in a
  sub-step ``h``), so a servo decelerating to rest lands in the band instead of
  chattering across zero;
- Stribeck friction (``plant.stribeck_friction`` ``F_St = F_s - F_c``,
  ``plant.stribeck_velocity`` ``v_St``): the sliding friction becomes the standard
  exponential Stribeck curve ``sign(dq) (F_c + F_St exp(-(dq/v_St)^2))`` (the
  "Gaussian" exponent of Armstrong-Helouvry), evaluated at the start of each
  sub-step and held over it like the Coulomb term. The Karnopp band is extended
  with the same rule at the static level ``F_s = F_c + F_St``: inside the band the
  servo sticks while the torque is within ``+-F_s`` and breaks away beyond it (the
  breakaway torque is ``F_s``); ``v_s`` defaults to ``2 F_s h / J``. With
  ``F_St = 0`` every number is the Coulomb model's, bit for bit;
- backlash (``plant.backlash``, the total dead band ``beta``): in a geared servo the
  encoder sits on the motor shaft and the play is in the gear, so the dead band is
  between the motor (whose position the sensors report and whose inertia ``J`` is
  the plant's) and a massless load that touches the environment. The load position
  ``q_l`` obeys the play operator ``|q - q_l| <= beta/2`` and starts centred. While the
  load is outside the environment it only moves when the motor pushes it; inside,
  a load pressed against one face of the gap transmits the environment's torque
  ``K (q_l - q_c) + D dq`` as long as that face can carry it (the pushing face a
  torque >= 0, the pulling face <= 0), and the motor then moves with the contact
  matrices in the shifted coordinate ``q_l = q -+ beta/2`` (exact ZOH within the
  sub-step); otherwise the gap opens, no torque reaches the motor, and the massless
  load relaxes with the environment's own time constant (``K q_l + D dq_l = 0``:
  ``q_l - q_c`` decays by ``exp(-K h/D)`` per sub-step, at once when ``D = 0``). The
  engagement is decided at the start of each sub-step, so crossing the dead band is
  placed within a sub-step, like a contact transition;
- the unknown disturbance ``tau_d^u(t)``: none, constant, step (``A`` from
  ``start``) or sine (``A sin(2 pi f (t - start))`` from ``start``, 0 before),
  sampled at the middle of each sub-step (exact for a step that starts on a
  sub-step boundary, second order for the sine).

When nothing nonlinear is active during a call (no friction, no backlash, the
disturbance constant over the call, and the mode unchanged at the end of the
call) the call is one exact ZOH step: with the servo in contact from the start it
is bit for bit the analysis' discretised plant ``x+ = Phi x + Gamma (u - tau_d^u)``.
A mode change inside such a call makes the call redo itself sub-stepped.

A coupling to other axes (:meth:`Plant.couple`, used by :mod:`dobhil.emulator.coupling`)
adds a spring ``K_k`` and damper ``D_k`` from the servo to a moving anchor, in both modes:
the plant's own part ``-K_k q - D_k dq`` is in the ZOH matrices (``servo_matrices`` and
``plant_matrices`` with the extra stiffness and damping, exact like the rest), the anchor's
part :attr:`Plant.coupling_input` ``= sum_j K_j q_j + D_j dq_j`` is an input torque held over
the call like the motor's (the coupling decides what to hold). An uncoupled plant runs the
very lines it ran before (bit for bit: tested).

The motor torque is clamped to ``plant.torque_limit`` and held over the call.
Sensor side: :attr:`Plant.position` is the true position rounded to the nearest
encoder count (``sensor.encoder_resolution`` counts per revolution, 0: exact);
:attr:`Plant.velocity` is the true velocity plus Gaussian noise of standard
deviation ``sensor.velocity_noise`` from ``numpy.random.default_rng(sensor.seed)``,
one draw per call (and one at construction), so a run is reproducible whatever
reads the sensors and how often. Both are plain attributes, refreshed by
:meth:`Plant.step`.

Hot path: the 2x2 ZOH matrices of each mode are precomputed per ``dt`` (and per
sub-step) with the synthesis functions and unpacked to Python floats; a call does
scalar arithmetic only.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from dobhil.config.schema import Config
from dobhil.synthesis.controller import discretize
from dobhil.synthesis.models import plant_matrices, servo_matrices
from dobhil.synthesis.params import Discretization

__all__ = ["DisturbanceKind", "Plant", "PlantTruth", "Propagator", "StepMatrices",
           "coulomb_substeps", "mode_propagators"]

_NOISE_BLOCK = 1024    # velocity noise is drawn in blocks of this many samples
_CACHE_SIZE = 64       # distinct dt values whose ZOH matrices are kept


class DisturbanceKind(IntEnum):
    """Profile of the unknown disturbance torque tau_d^u (``plant.disturbance``)."""

    NONE = 0
    CONSTANT = 1
    STEP = 2
    SINE = 3


@dataclass(frozen=True)
class PlantTruth:
    """Ground truth of the emulated plant at one instant (SI units)."""

    q: float          # true position [rad]
    dq: float         # true velocity [rad/s]
    tau_motor: float  # motor torque applied over the last step, after the clamp [N m]
    tau_int: float    # interaction torque with the environment [N m]
    t: float          # emulator time [s]


@dataclass(frozen=True)
class Propagator:
    """ZOH of one mode over one interval: ``x+ = [[p00, p01], [p10, p11]] x + [g0, g1] w``."""

    p00: float
    p01: float
    p10: float
    p11: float
    g0: float
    g1: float

    @classmethod
    def of(cls, a: np.ndarray, b: np.ndarray, h: float) -> Propagator:
        phi, gamma = discretize(a, b, h, Discretization.ZOH)
        return cls.of_zoh(phi, gamma)

    @classmethod
    def of_zoh(cls, phi: np.ndarray, gamma: np.ndarray) -> Propagator:
        """The propagator of one mode's ZOH ``phi`` (2x2), ``gamma`` (2x1)."""
        return cls(float(phi[0, 0]), float(phi[0, 1]), float(phi[1, 0]), float(phi[1, 1]),
                   float(gamma[0, 0]), float(gamma[1, 0]))


@dataclass(frozen=True)
class StepMatrices:
    """Everything a call with one ``dt`` needs (:meth:`Plant.matrices`): the ZOH of each mode
    over the whole call and over one sub-step, the sub-step length, the Karnopp band and the
    backlash relaxation. Public so a faster simulator of the same plant
    (:mod:`dobhil.identify.model`) uses these very numbers instead of discretising again."""

    free: Propagator       # whole dt, free motion
    contact: Propagator    # whole dt, in contact
    free_sub: Propagator   # one sub-step
    contact_sub: Propagator
    h: float               # sub-step length
    stiction: float        # stiction band v_s [rad/s]
    relax: float           # backlash: decay of a detached load's penetration per sub-step


class Plant:
    """The emulated servo plus environment (see the module docstring)."""

    position: float  # measured position [rad] (quantised)
    velocity: float  # measured velocity [rad/s] (noisy)

    def __init__(self, *, inertia: float, viscous_friction: float = 0.0,
                 coulomb_friction: float = 0.0, torque_limit: float = math.inf,
                 stiffness: float = 0.0, damping: float = 0.0, contact_position: float = 0.0,
                 initial_position: float = 0.0, initial_velocity: float = 0.0,
                 disturbance: DisturbanceKind = DisturbanceKind.NONE,
                 disturbance_amplitude: float = 0.0, disturbance_frequency: float = 1.0,
                 disturbance_start: float = 0.0, encoder_resolution: int = 0,
                 velocity_noise: float = 0.0, seed: int = 0, substeps: int = 10,
                 stiction_velocity: float | None = None, stribeck_friction: float = 0.0,
                 stribeck_velocity: float = 0.05, backlash: float = 0.0) -> None:
        if inertia <= 0:
            raise ValueError(f"inertia: expected > 0 kg m^2, got {inertia}")
        if substeps < 1:
            raise ValueError(f"substeps: expected >= 1, got {substeps}")
        if torque_limit <= 0:
            raise ValueError(f"torque_limit: expected > 0 N m, got {torque_limit}")
        if stribeck_velocity <= 0:
            raise ValueError(f"stribeck_velocity: expected > 0 rad/s, got {stribeck_velocity}")
        if backlash < 0:
            raise ValueError(f"backlash: expected >= 0 rad, got {backlash}")
        self.inertia = float(inertia)
        self.viscous_friction = float(viscous_friction)
        self.coulomb_friction = float(coulomb_friction)
        self.stribeck_friction = float(stribeck_friction)
        self.stribeck_velocity = float(stribeck_velocity)
        self.backlash = float(backlash)
        # any friction sends every call through the sub-steps
        self._friction = self.coulomb_friction != 0.0 or self.stribeck_friction != 0.0
        # no Stribeck peak: the sub-steps take the written-out loop (_coulomb_substeps)
        self._coulomb_only = self.stribeck_friction == 0.0
        self.torque_limit = float(torque_limit)
        self.stiffness = float(stiffness)
        self.damping = float(damping)
        self.contact_position = float(contact_position)
        self.initial_position = float(initial_position)
        self.initial_velocity = float(initial_velocity)
        self.disturbance = DisturbanceKind(disturbance)
        self.disturbance_amplitude = float(disturbance_amplitude)
        self.disturbance_frequency = float(disturbance_frequency)
        self.disturbance_start = float(disturbance_start)
        self.encoder_resolution = int(encoder_resolution)
        self.velocity_noise = float(velocity_noise)
        self.seed = int(seed)
        self.substeps = int(substeps)
        self.stiction_velocity = stiction_velocity
        self._a_free, self._b_free = servo_matrices(self.inertia, self.viscous_friction)
        self._a_contact, self._b_contact, _ = plant_matrices(
            self.inertia, self.viscous_friction, self.stiffness, self.damping)
        self._count = (2.0 * math.pi / self.encoder_resolution) if self.encoder_resolution else 0.0
        self._omega = 2.0 * math.pi * self.disturbance_frequency
        self._cache: dict[float, StepMatrices] = {}
        self._dt = math.nan
        self._zoh: StepMatrices | None = None
        #: coupling to other axes (:meth:`couple`): the spring and damper to the anchor
        self.coupling_stiffness = 0.0
        self.coupling_damping = 0.0
        #: [N m] the anchor's part of the coupling torque, held over the next step
        self.coupling_input = 0.0
        self.reset()

    @classmethod
    def from_config(cls, config: Config, *, substeps: int = 10,
                    stiction_velocity: float | None = None) -> Plant:
        """The plant of ``config.plant``, ``config.environment`` and ``config.sensor``."""
        p, env, s = config.plant, config.environment, config.sensor
        return cls(inertia=p.inertia, viscous_friction=p.viscous_friction,
                   coulomb_friction=p.coulomb_friction, torque_limit=p.torque_limit,
                   stiffness=env.stiffness, damping=env.damping,
                   contact_position=env.contact_position, initial_position=p.initial_position,
                   disturbance=DisturbanceKind[p.disturbance.upper()],
                   disturbance_amplitude=p.disturbance_amplitude,
                   disturbance_frequency=p.disturbance_frequency,
                   disturbance_start=p.disturbance_start,
                   encoder_resolution=s.encoder_resolution, velocity_noise=s.velocity_noise,
                   seed=s.seed, substeps=substeps, stiction_velocity=stiction_velocity,
                   stribeck_friction=p.stribeck_friction, stribeck_velocity=p.stribeck_velocity,
                   backlash=p.backlash)

    def couple(self, stiffness: float, damping: float) -> None:
        """Join the servo to a moving anchor by a spring ``stiffness`` [N m/rad] and a damper
        ``damping`` [N m s/rad] (the sum over the axes it is coupled to); each step then adds
        ``coupling_input - stiffness q - damping dq`` to the torques (module docstring)."""
        if not (stiffness >= 0.0 and damping >= 0.0 and math.isfinite(stiffness + damping)):
            raise ValueError(f"coupling: expected finite stiffness and damping >= 0, got {stiffness}, {damping}")
        if self.backlash and (stiffness or damping):
            raise ValueError("coupling: a plant with backlash cannot be coupled (its load is massless)")
        self.coupling_stiffness, self.coupling_damping = float(stiffness), float(damping)
        j, b = self.inertia, self.viscous_friction
        if stiffness or damping:
            self._a_free, self._b_free, _ = plant_matrices(j, b + damping, stiffness, 0.0)
        else:
            self._a_free, self._b_free = servo_matrices(j, b)
        self._a_contact, self._b_contact, _ = plant_matrices(
            j, b + damping, self.stiffness + stiffness, self.damping)
        self._coulomb_only = self.stribeck_friction == 0.0 and not (stiffness or damping)
        self._cache.clear()
        self._dt, self._zoh = math.nan, None

    # -- state ----------------------------------------------------------------

    def reset(self) -> None:
        """Back to the initial position and velocity (at rest unless ``initial_velocity``
        is set), time 0, the noise sequence restarted."""
        self._e = self.initial_position - self.contact_position
        self._dq = self.initial_velocity
        self._load_e = self._e   # backlash: the load, centred in the dead band
        self._side = 0           # backlash: +1/-1 load against the motor's pushing/pulling face
        self._t = 0.0
        self._tau_motor = 0.0
        self._tau_coulomb = 0.0
        self._rng = np.random.default_rng(self.seed)
        self._noise: list[float] = []
        self._noise_index = 0
        self._noise_value = 0.0
        self._sense()

    def set_state(self, position: float, velocity: float) -> None:
        """Put the servo at the true ``position`` [rad] with the true ``velocity`` [rad/s],
        keeping the time and the noise sequence (a simulation that starts a segment in
        motion, or continues a run computed elsewhere, moves the state only). With backlash
        the load is put in the middle of the dead band, as at :meth:`reset`. The sensors
        are refreshed with the current noise sample: no draw, so the sequence a run sees
        does not depend on how often its state was set."""
        self._e = float(position) - self.contact_position
        self._dq = float(velocity)
        self._load_e = self._e
        self._side = 0
        q = self._e + self.contact_position
        c = self._count
        self.position = round(q / c) * c if c else q
        self.velocity = self._dq + self.velocity_noise * self._noise_value

    @property
    def time(self) -> float:
        return self._t

    @property
    def true_position(self) -> float:
        return self._e + self.contact_position

    @property
    def true_velocity(self) -> float:
        return self._dq

    @property
    def load_position(self) -> float:
        """Position of the load behind the backlash (the motor's without backlash)."""
        return (self._load_e if self.backlash else self._e) + self.contact_position

    @property
    def in_contact(self) -> bool:
        """The load (the motor without backlash) is inside the environment."""
        return (self._load_e if self.backlash else self._e) >= 0.0

    @property
    def motor_torque(self) -> float:
        """Torque applied over the last step (after the clamp)."""
        return self._tau_motor

    @property
    def friction_torque(self) -> float:
        """Coulomb (and Stribeck) friction torque over the last sub-step (opposing the motion)."""
        return self._tau_coulomb

    @property
    def interaction_torque(self) -> float:
        """``K (q - q_c) + D dq`` in contact, 0 in free motion; with backlash the torque
        the load transmits to the motor (0 while the gap is open)."""
        if self.backlash:
            return self._transmitted(self._load_e, self._side, self._dq)
        e = self._e
        return self.stiffness * e + self.damping * self._dq if e >= 0.0 else 0.0

    @property
    def disturbance_torque(self) -> float:
        """tau_d^u at the current time."""
        return self.disturbance_at(self._t)

    def truth(self) -> PlantTruth:
        return PlantTruth(q=self.true_position, dq=self._dq, tau_motor=self._tau_motor,
                          tau_int=self.interaction_torque, t=self._t)

    def disturbance_at(self, t: float) -> float:
        """The disturbance profile tau_d^u(t)."""
        kind = self.disturbance
        if kind is DisturbanceKind.NONE:
            return 0.0
        if kind is DisturbanceKind.CONSTANT:
            return self.disturbance_amplitude
        if t < self.disturbance_start:
            return 0.0
        if kind is DisturbanceKind.STEP:
            return self.disturbance_amplitude
        return self.disturbance_amplitude * math.sin(self._omega * (t - self.disturbance_start))

    # -- integration ----------------------------------------------------------

    def matrices(self, dt: float) -> StepMatrices:
        """The ZOH matrices, sub-step and Karnopp band :meth:`step` uses for a call of
        ``dt`` seconds (computed once per ``dt``, then cached)."""
        return self._load(dt)

    def prepare(self, dt: float) -> None:
        """Compute the ZOH matrices of ``dt`` now (the first :meth:`step` of a new ``dt``
        otherwise does it: four matrix exponentials, tens of ms on a loaded machine)."""
        self._load(dt)

    def step(self, torque_nm: float, dt: float) -> None:
        """Advance ``dt`` seconds with the motor torque ``torque_nm`` (clamped) held."""
        lim = self.torque_limit
        u = lim if torque_nm > lim else (-lim if torque_nm < -lim else float(torque_nm))
        self._tau_motor = u
        zoh = self._zoh if dt == self._dt and self._zoh is not None else self._load(dt)
        t0 = self._t
        tau_d = self._constant_disturbance(t0, dt)
        if self.coupling_stiffness or self.coupling_damping:
            # the anchor's part, in the state's coordinate e = q - q_c: held like u
            u += self.coupling_input - self.coupling_stiffness * self.contact_position
        if self.backlash:
            self._backlash_substeps(u, tau_d, t0, zoh)
        elif tau_d is None or self._friction or not self._exact_step(u - tau_d, zoh):
            self._substeps(u, tau_d, t0, zoh)
        self._t = t0 + dt
        self._sense()

    def _exact_step(self, w: float, zoh: StepMatrices) -> bool:
        """One ZOH step in the current mode; False (state untouched) if the mode changed."""
        e, dq = self._e, self._dq
        contact = e >= 0.0
        p = zoh.contact if contact else zoh.free
        ne = p.p00 * e + p.p01 * dq + p.g0 * w
        if (ne >= 0.0) is not contact:
            return False
        self._e = ne
        self._dq = p.p10 * e + p.p11 * dq + p.g1 * w
        self._tau_coulomb = 0.0
        return True

    def _constant_disturbance(self, t0: float, dt: float) -> float | None:
        """tau_d^u if it is constant over ``[t0, t0 + dt]``, else None."""
        kind = self.disturbance
        if kind is DisturbanceKind.NONE:
            return 0.0
        if kind is DisturbanceKind.CONSTANT:
            return self.disturbance_amplitude
        if kind is DisturbanceKind.STEP and not t0 < self.disturbance_start < t0 + dt:
            return self.disturbance_at(t0 + 0.5 * dt)
        return None

    def _substeps(self, u: float, tau_d: float | None, t0: float, zoh: StepMatrices) -> None:
        """``substeps`` ZOH sub-steps; ``tau_d`` the disturbance if constant over the call."""
        if tau_d is not None and self._coulomb_only:
            self._coulomb_substeps(u - tau_d, zoh)
            return
        e, dq = self._e, self._dq
        h, vs, friction = zoh.h, zoh.stiction, self._friction
        kf = self.coupling_stiffness       # the spring acting in both modes (0: uncoupled)
        k = self.stiffness + kf
        pc, pf = zoh.contact_sub, zoh.free_sub
        tau_c = 0.0
        for i in range(self.substeps):
            w = u - (tau_d if tau_d is not None else self.disturbance_at(t0 + (i + 0.5) * h))
            contact = e >= 0.0
            if friction:
                rest = w - k * e if contact else (w - kf * e if kf else w)
                tau_c, stuck = self._friction_at(dq, rest, vs)
                if stuck:                  # friction balances the torque
                    dq = 0.0
                    continue
                w -= tau_c
            p = pc if contact else pf
            e, dq = (p.p00 * e + p.p01 * dq + p.g0 * w,
                     p.p10 * e + p.p11 * dq + p.g1 * w)
        self._e, self._dq, self._tau_coulomb = e, dq, tau_c

    def _coulomb_substeps(self, w0: float, zoh: StepMatrices) -> None:
        """:meth:`_substeps` when the disturbance is constant over the call and the friction
        is Coulomb's alone (or none): :func:`coulomb_substeps`, the same arithmetic in the
        same order as the general loop (bit for bit: tested), ~1.5x faster (measured: 6 vs
        9 us per call of ten sub-steps)."""
        c, f = zoh.contact_sub, zoh.free_sub
        self._e, self._dq, self._tau_coulomb = coulomb_substeps(
            self._e, self._dq, w0, self.substeps, zoh.stiction, self.coulomb_friction,
            self.stiffness, self._friction, c.p00, c.p01, c.p10, c.p11, c.g0, c.g1,
            f.p00, f.p01, f.p10, f.p11, f.g0, f.g1)

    def _friction_at(self, dq: float, f: float, vs: float) -> tuple[float, bool]:
        """Friction torque over a sub-step starting at velocity ``dq``, ``f`` the rest of the
        torque acting at zero velocity; True when the servo sticks (friction is then ``f``).

        Sliding: Coulomb plus the Stribeck peak, ``F_c + F_St exp(-(dq/v_St)^2)``; inside
        the Karnopp band ``|dq| <= vs``: stuck while ``|f| <= F_s = F_c + F_St``, else
        ``F_s`` against ``f`` (the curve's value at rest). ``F_St = 0``: the Coulomb
        model's numbers exactly (no exponential is evaluated).
        """
        fc, fst = self.coulomb_friction, self.stribeck_friction
        if dq > vs or dq < -vs:
            level = fc + fst * math.exp(-(dq / self.stribeck_velocity) ** 2) if fst else fc
            return (level if dq > 0.0 else -level), False
        fs = fc + fst
        if -fs <= f <= fs:
            return f, True
        return (fs if f > 0.0 else -fs), False

    def _transmitted(self, load_e: float, side: int, dq: float) -> float:
        """Backlash: the environment's torque the load passes to the motor (0: gap open).

        The load is massless, so it passes ``K (q_l - q_c) + D dq`` only when it is inside
        the environment, lies against a face of the gap (``side``) and that face can carry
        the torque's sign (pushing face >= 0, pulling face <= 0).
        """
        if load_e < 0.0 or side == 0:
            return 0.0
        tau = self.stiffness * load_e + self.damping * dq
        return tau if tau * side >= 0.0 else 0.0

    def _backlash_substeps(self, u: float, tau_d: float | None, t0: float, zoh: StepMatrices) -> None:
        """Sub-steps with the dead band between motor and load (module docstring)."""
        e, dq, load_e, side = self._e, self._dq, self._load_e, self._side
        h, vs, friction, relax = zoh.h, zoh.stiction, self._friction, zoh.relax
        k, d, half = self.stiffness, self.damping, 0.5 * self.backlash
        pc, pf = zoh.contact_sub, zoh.free_sub
        tau_c = 0.0
        for i in range(self.substeps):
            w = u - (tau_d if tau_d is not None else self.disturbance_at(t0 + (i + 0.5) * h))
            # engaged (the rule of _transmitted): the face the load lies on carries the torque
            if side != 0 and load_e >= 0.0 and side * (k * load_e + d * dq) >= 0.0:
                # the contact plant in the load's coordinate q_l - q_c = q - q_c - side*beta/2
                x = load_e
                if friction:
                    tau_c, stuck = self._friction_at(dq, w - k * x, vs)
                    if stuck:
                        dq = 0.0
                        continue
                    w -= tau_c
                x, dq = (pc.p00 * x + pc.p01 * dq + pc.g0 * w,
                         pc.p10 * x + pc.p11 * dq + pc.g1 * w)
                e, load_e = x + side * half, x
                continue
            stuck = False
            if friction:
                tau_c, stuck = self._friction_at(dq, w, vs)
                w -= tau_c
            if stuck:
                dq = 0.0
            else:
                e, dq = (pf.p00 * e + pf.p01 * dq + pf.g0 * w,
                         pf.p10 * e + pf.p11 * dq + pf.g1 * w)
            if load_e > 0.0:          # detached inside the environment: K q_l + D dq_l = 0
                load_e *= relax
            # the play operator: the motor's faces push the load along
            if load_e <= e - half:
                load_e, side = e - half, 1
            elif load_e >= e + half:
                load_e, side = e + half, -1
            else:
                side = 0
        self._e, self._dq, self._load_e, self._side, self._tau_coulomb = (
            e, dq, load_e, side, tau_c)

    def _load(self, dt: float) -> StepMatrices:
        """The ZOH matrices for ``dt`` (cached)."""
        zoh = self._cache.get(dt)
        if zoh is None:
            zoh = self._compute([dt])[0]
        self._dt, self._zoh = dt, zoh
        return zoh

    def _compute(self, dts: list[float]) -> list[StepMatrices]:
        """The ZOH matrices of each of ``dts`` (each > 0), cached: the free and contact
        modes over the call and over one sub-step, all in one batched exponential."""
        for dt in dts:
            if not dt > 0.0:
                raise ValueError(f"dt: expected > 0 s, got {dt}")
        if len(self._cache) + len(dts) > _CACHE_SIZE:
            self._cache.clear()
        subs = [dt / self.substeps for dt in dts]
        # rows per dt: free over dt, contact over dt, free over h, contact over h
        modes = ((self._a_free, self._b_free), (self._a_contact, self._b_contact))
        props = _propagators([(a, b, span) for dt, h in zip(dts, subs) for span in (dt, h) for a, b in modes])
        k, d = self.stiffness, self.damping
        out = []
        for i, (dt, h) in enumerate(zip(dts, subs)):
            vs = (self.stiction_velocity if self.stiction_velocity is not None
                  else 2.0 * (self.coulomb_friction + self.stribeck_friction) * h / self.inertia)
            relax = math.exp(-k * h / d) if d > 0.0 else (0.0 if k > 0.0 else 1.0)
            free, contact, free_sub, contact_sub = props[4 * i: 4 * i + 4]
            zoh = StepMatrices(free=free, contact=contact, free_sub=free_sub, contact_sub=contact_sub,
                               h=h, stiction=vs, relax=relax)
            self._cache[dt] = zoh
            out.append(zoh)
        return out

    # -- sensors --------------------------------------------------------------

    def _sense(self) -> None:
        q = self._e + self.contact_position
        c = self._count
        self.position = round(q / c) * c if c else q
        noise = self.velocity_noise
        if noise:
            self._noise_value = self._draw()
            self.velocity = self._dq + noise * self._noise_value
        else:
            self.velocity = self._dq

    def _draw(self) -> float:
        i = self._noise_index
        if i >= len(self._noise):
            self._noise = self._rng.standard_normal(_NOISE_BLOCK).tolist()
            i = 0
        self._noise_index = i + 1
        return self._noise[i]


#: the propagators of recent modes and spans, shared by every Plant (:func:`_propagators`)
_PROPAGATORS: OrderedDict[tuple[bytes, bytes, float], Propagator] = OrderedDict()
_PROPAGATORS_LOCK = threading.Lock()
#: how many :data:`_PROPAGATORS` keeps, least recently used dropped first (measured: a
#: closed-loop fit of a 4 s force run asked 10704, of which 6020 distinct; 64 kept found
#: 42 % of them, all of them 44 %)
_PROPAGATORS_SIZE = 256


#: one call's propagators: free and contact over the call, free and contact over a sub-step
CallPropagators = tuple[Propagator, Propagator, Propagator, Propagator]


def mode_propagators(inertia: float, viscous_friction: float, stiffness: float, damping: float,
                     dts: list[float], substeps: int = 10) -> list[CallPropagators]:
    """Per call of each of ``dts``: the ZOH ``(free, contact, free_sub, contact_sub)`` of an
    uncoupled plant of these parameters -- the numbers of ``Plant(...).matrices(dt)``
    (the same matrices through :func:`_propagators`), without a Plant's set-up (its state,
    its noise generator: a quarter of a simulation in
    :func:`dobhil.identify.closedloop.simulate_loop`, which needs only these)."""
    if not inertia > 0:
        raise ValueError(f"inertia: expected > 0 kg m^2, got {inertia}")
    a_free, b_free = servo_matrices(float(inertia), float(viscous_friction))
    a_contact, b_contact, _ = plant_matrices(float(inertia), float(viscous_friction), float(stiffness), float(damping))
    modes = ((a_free, b_free), (a_contact, b_contact))
    props = _propagators([(a, b, span) for dt in dts for span in (dt, dt / substeps) for a, b in modes])
    return [(props[4 * i], props[4 * i + 1], props[4 * i + 2], props[4 * i + 3]) for i in range(len(dts))]


def _propagators(rows: list[tuple[np.ndarray, np.ndarray, float]]) -> list[Propagator]:
    """The ZOH :class:`Propagator` of each ``(A, B, span)``: those seen recently from a
    process-wide cache, the rest by one batched :func:`discretize` (``scipy.linalg.expm``
    runs its algorithm on each matrix of a stack alone: each is bit for bit the one a call
    of its own gives). Why: the identification builds a Plant for every candidate it
    simulates, and the matrix exponentials were most of a simulation of a few thousand
    samples; a candidate that moves only the environment (or only the servo) keeps the
    other mode's propagators, and a central difference returns to the point it left."""
    keys = [(a.tobytes(), b.tobytes(), float(span)) for a, b, span in rows]
    found: dict[tuple[bytes, bytes, float], Propagator] = {}
    with _PROPAGATORS_LOCK:
        for key in keys:
            prop = _PROPAGATORS.get(key)
            if prop is not None:
                _PROPAGATORS.move_to_end(key)
                found[key] = prop
    todo = {key: row for key, row in zip(keys, rows) if key not in found}
    if todo:
        picked = list(todo.values())
        phi, gamma = discretize(np.stack([a for a, _, _ in picked]), np.stack([b for _, b, _ in picked]),
                                np.array([span for _, _, span in picked]).reshape(-1, 1, 1), Discretization.ZOH)
        new = {key: Propagator.of_zoh(phi[i], gamma[i]) for i, key in enumerate(todo)}
        found.update(new)
        with _PROPAGATORS_LOCK:
            _PROPAGATORS.update(new)
            while len(_PROPAGATORS) > _PROPAGATORS_SIZE:
                _PROPAGATORS.popitem(last=False)
    return [found[key] for key in keys]


def coulomb_substeps(e: float, dq: float, w0: float, substeps: int, vs: float, fc: float,
                     k: float, friction: bool, c00: float, c01: float, c10: float, c11: float,
                     cg0: float, cg1: float, f00: float, f01: float, f10: float, f11: float,
                     fg0: float, fg1: float) -> tuple[float, float, float]:
    """One call of :meth:`Plant.step` with Coulomb friction (or none) and a constant
    disturbance: ``substeps`` ZOH sub-steps of the contact (``c..``) or free (``f..``)
    propagator (:class:`Propagator` fields) chosen by the sign of ``e = q - q_c`` at each
    sub-step's start, ``w0`` the torque less the disturbance, the Karnopp band ``vs``.
    Returns ``(e, dq, friction torque of the last sub-step)``.

    :meth:`Plant._friction_at`'s decision with no Stribeck peak, written out, and scalars
    only: plain Python for the Plant, and the one source the identification compiles with
    numba when it is installed (dobhil.identify.model) -- so both run these very lines."""
    tau_c = 0.0
    for _ in range(substeps):
        w = w0
        contact = e >= 0.0
        if friction:
            if dq > vs or dq < -vs:
                tau_c = fc if dq > 0.0 else -fc
            else:
                rest = w - k * e if contact else w
                if -fc <= rest <= fc:          # friction balances the torque: stuck
                    tau_c = rest
                    dq = 0.0
                    continue
                tau_c = fc if rest > 0.0 else -fc
            w -= tau_c
        if contact:
            e, dq = c00 * e + c01 * dq + cg0 * w, c10 * e + c11 * dq + cg1 * w
        else:
            e, dq = f00 * e + f01 * dq + fg0 * w, f10 * e + f11 * dq + fg1 * w
    return e, dq, tau_c
