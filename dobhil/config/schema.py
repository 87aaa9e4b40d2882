"""Every configuration key of dobhil, in one place.

The frozen dataclasses below *are* the key table: a key ``section.name`` is the
field ``name`` of the section dataclass, and its ``metadata`` says the unit, what
values are allowed and what it means. ``dobhil.config.load`` validates YAML and
``--set key=value`` overrides against these fields; ``docs/config.md`` is
generated from them (``python tools/gen_config_doc.py``). All values are SI.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any


class Check(IntEnum):
    """What values a numeric key allows."""

    ANY = 0
    POSITIVE = 1
    NONNEGATIVE = 2


def key(default: Any, doc: str, *, unit: str = "", check: Check = Check.ANY,
        choices: tuple[str, ...] = (), structural: bool = False,
        maximum: float | None = None, minimum: float | None = None) -> Any:
    """A config key: a dataclass field carrying its documentation and constraint.

    ``structural`` keys change the shape of the synthesised matrices (model
    kinds, delay length) and cannot be swept. ``maximum``: the largest physically
    meaningful value (checked by :func:`check_maximum`). ``minimum``: the smallest value:
    of a key whose ``check`` is :attr:`Check.ANY`, a count from 0 with -1 for "none" (e.g.
    ``loop.cpu_affinity``); of a positive key, the smallest physically meaningful value
    (below it the loop's matrices overflow or turn singular while the key looks valid);
    both checked by :func:`check_minimum`.
    """
    if minimum is not None and check is not Check.ANY:
        doc = f"{doc}; at least {minimum:g}"
    if maximum is not None:
        doc = f"{doc}; at most {maximum:g}"
    meta = {"doc": doc, "unit": unit, "check": check, "choices": choices,
            "structural": structural or bool(choices), "maximum": maximum, "minimum": minimum}
    return field(default=default, metadata=meta)


def allowed_range(meta: Any) -> str:
    """The values a numeric key allows, as the refusals and docs/config.md say them
    (``> 0``, ``>= -1``, ``>= 0 and <= 99``, ``any``)."""
    low = {Check.POSITIVE: "> 0", Check.NONNEGATIVE: ">= 0"}.get(meta["check"], "")
    if meta.get("minimum") is not None:
        low = f">= {meta['minimum']:g}"
    top = meta.get("maximum")
    if top is None:
        return low or "any"
    return f"{low} and <= {top:g}" if low else f"<= {top:g}"


def check_maximum(name: str, value: float, meta: Any) -> str | None:
    """The one-line complaint when ``value`` exceeds the key's ``maximum`` (else None)."""
    top = meta.get("maximum")
    if top is None or value <= top:
        return None
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    return f"{name} = {value!r}: out of range; allowed: {allowed_range(meta)}{unit}"


def check_minimum(name: str, value: float, meta: Any) -> str | None:
    """The one-line complaint when ``value`` is below the key's ``minimum`` (else None); a
    key of :attr:`Check.ANY`'s ends with the key's documentation, which says what the
    smallest value stands for."""
    low = meta.get("minimum")
    if low is None or value >= low:
        return None
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    line = f"{name} = {value!r}: out of range; allowed: {allowed_range(meta)}{unit}"
    return f"{line}; {meta['doc']}" if meta["check"] is Check.ANY else line


def span_problem(label: str, lo: float, hi: float, meta: Any) -> str | None:
    """The one-line complaint when values from ``lo`` to ``hi`` are not all allowed for the
    key (its ceiling, floor and sign; ``label`` names the option and key), else None: the
    one check of a range of values that ``sweep --vary``, ``tune --range``/``--bound`` and
    a campaign's distributions each take."""
    problem = check_maximum(label, hi, meta) or check_minimum(label, lo, meta)
    if problem is not None:
        return problem
    if meta["check"] is Check.POSITIVE and not lo > 0:
        return f"{label}: every value must be > 0 (got {lo:g})"
    if meta["check"] is Check.NONNEGATIVE and not lo >= 0:
        return f"{label}: every value must be >= 0 (got {lo:g})"
    return None


#: the smallest inertia a servo has (kg m^2): two decades below the rotors of the smallest
#: micro-motors (2 to 4 mm across: about 1e-10 kg m^2, 0.001 g cm^2); far below it 1/J_m
#: overflows the loop's matrices (1/J_m is inf at J_m = 1e-300)
MIN_INERTIA = 1e-12
#: the smallest filter or observer bandwidth (rad/s): a time constant of 1000 s, longer than
#: any run, and the low end of tune's default search at the longest loop.period (0.01 / 10 s,
#: dobhil/tune/problem.py); far below it the sampled observer's pole exp(-g T) rounds to 1
#: and its matrices turn singular (1e-15 rad/s at T = 1 ms)
MIN_BANDWIDTH = 1e-3

#: the shortest control period (s): the time the shortest frame takes on the fastest CAN bus,
#: so that a period can carry at least its torque command. A CAN FD frame of no data, its data
#: phase taken as instant, is 34 bits at the nominal rate (arbitration 17 and its 4 stuff
#: bits, CRC delimiter, ACK, EOF, IFS: fd_frame_bits in dobhil/drives/bus_load.py); the
#: nominal rate is at most 1 Mbit/s (ISO 11898-1; drive.bitrate's ceiling). The sampled
#: model resolves it: exp(-g T) of the slowest bandwidth is 1 - 3.4e-8, of the fastest 0.
MIN_PERIOD = 34e-6


@dataclass(frozen=True)
class PlantConfig:
    """The exact servo (the emulator's plant; J_m, b_m of the paper)."""

    inertia: float = key(0.25, "exact inertia J_m", unit="kg m^2", check=Check.POSITIVE,
                          minimum=MIN_INERTIA, maximum=1e6)
    viscous_friction: float = key(0.0, "exact viscous friction b_m", unit="N m s/rad",
                                  check=Check.NONNEGATIVE, maximum=1e7)
    coulomb_friction: float = key(0.0, "Coulomb friction (emulator only, unmodelled by the analysis)",
                                  unit="N m", check=Check.NONNEGATIVE)
    stribeck_friction: float = key(0.0, "static friction above the Coulomb level F_s - F_c: "
                                   "friction F_c + (F_s - F_c) exp(-(v/v_St)^2) (emulator "
                                   "only, unmodelled by the analysis)", unit="N m",
                                   check=Check.NONNEGATIVE)
    stribeck_velocity: float = key(0.05, "Stribeck velocity v_St: the Stribeck peak decays "
                                   "over this velocity (emulator only)", unit="rad/s",
                                   check=Check.POSITIVE)
    backlash: float = key(0.0, "total dead band of the gear between the motor (and its encoder) "
                          "and the load touching the environment (emulator only, unmodelled "
                          "by the analysis)", unit="rad", check=Check.NONNEGATIVE, maximum=1.0)
    torque_limit: float = key(50.0, "motor torque limit of the emulated drive", unit="N m",
                              check=Check.POSITIVE)
    initial_position: float = key(0.0, "emulated initial position", unit="rad")
    disturbance: str = key("none", "unknown disturbance torque profile tau_d^u (emulator)",
                           choices=("none", "constant", "step", "sine"))
    disturbance_amplitude: float = key(0.0, "amplitude of the disturbance torque", unit="N m")
    disturbance_frequency: float = key(1.0, "frequency of a sine disturbance", unit="Hz",
                                       check=Check.POSITIVE)
    disturbance_start: float = key(0.0, "time at which a step disturbance starts", unit="s",
                                   check=Check.NONNEGATIVE)


@dataclass(frozen=True)
class EnvironmentConfig:
    """The environment touched by the servo: a spring-damper (D_env, K_env)."""

    stiffness: float = key(1.0e4, "environment stiffness K_env", unit="N m/rad",
                           check=Check.NONNEGATIVE, maximum=1e10)
    damping: float = key(50.0, "environment damping D_env", unit="N m s/rad",
                         check=Check.NONNEGATIVE, maximum=1e7)
    contact_position: float = key(0.0, "position at which the environment engages (emulator)",
                                  unit="rad")


@dataclass(frozen=True)
class DesignConfig:
    """The controller: DOb, RTOb, force gain, velocity source, sampling."""

    nominal_inertia: float = key(0.25, "nominal inertia J_mn of the DOb", unit="kg m^2",
                                 check=Check.POSITIVE, maximum=1e6)
    nominal_friction: float = key(0.0, "nominal viscous friction b_mn of the DOb",
                                  unit="N m s/rad", check=Check.NONNEGATIVE, maximum=1e7)
    identified_inertia: float = key(0.25, "identified inertia J_mi of the RTOb", unit="kg m^2",
                                    check=Check.POSITIVE, maximum=1e6)
    identified_friction: float = key(0.0, "identified viscous friction b_mi of the RTOb",
                                     unit="N m s/rad", check=Check.NONNEGATIVE, maximum=1e7)
    dob_bandwidth: float = key(500.0, "DOb bandwidth g_DOb", unit="rad/s", check=Check.POSITIVE,
                               minimum=MIN_BANDWIDTH, maximum=1e7)
    rtob_bandwidth: float = key(500.0, "RTOb bandwidth g_RTOb", unit="rad/s",
                                check=Check.POSITIVE, minimum=MIN_BANDWIDTH, maximum=1e7)
    force_gain: float = key(2.0, "proportional force gain C_f", check=Check.NONNEGATIVE,
                            maximum=1e6)
    disturbance_model: str = key("constant", "disturbance model (A_D, C_D) of the DOb",
                                 choices=("constant", "ramp", "sinusoid"))
    disturbance_frequency: float = key(10.0, "frequency of the DOb's sinusoid model",
                                       unit="rad/s", check=Check.POSITIVE, maximum=1e7)
    interaction_model: str = key("constant", "interaction torque model (A_R, C_R) of the RTOb",
                                 choices=("constant", "ramp", "sinusoid"))
    interaction_frequency: float = key(10.0, "frequency of the RTOb's sinusoid model",
                                       unit="rad/s", check=Check.POSITIVE, maximum=1e7)
    velocity_source: str = key("measured", "velocity fed to the observers",
                               choices=("measured", "estimated"))
    velocity_filter_bandwidth: float = key(2000.0, "bandwidth g_v of the velocity estimate "
                                           "g_v s/(s+g_v) q", unit="rad/s", check=Check.POSITIVE,
                                           minimum=MIN_BANDWIDTH, maximum=1e8)
    delay_samples: int = key(0, "transport delay of the torque command in whole samples",
                             check=Check.NONNEGATIVE, structural=True, maximum=20)
    discretization: str = key("parabolic", "how the controller is sampled: torque by zero-order "
                              "hold; measured signals by a parabola through the last, this and "
                              "the next sample (parabolic: exact inertia and friction), a "
                              "triangle (foh: ramp-invariant), held (zoh) or forward Euler (euler)",
                              choices=("parabolic", "foh", "zoh", "euler"))
    input_delay: float = key(0.0, "fraction of a period between the feedback sample and the "
                             "torque reaching the plant (compute + bus latency); below "
                             "loop.period", unit="s", check=Check.NONNEGATIVE, structural=True)


@dataclass(frozen=True)
class LoopConfig:
    """The runtime loop."""

    period: float = key(1.0e-3, "control period T_s (no shorter than one CAN frame takes at 1 Mbit/s)",
                        unit="s", check=Check.POSITIVE, minimum=MIN_PERIOD, maximum=10.0)
    duration: float = key(1.0, "run duration", unit="s", check=Check.POSITIVE)
    feedback_timeout: float = key(5.0e-3, "no fresh feedback for this long stops the run",
                                  unit="s", check=Check.POSITIVE)
    torque_limit: float = key(20.0, "host-side torque saturation", unit="N m",
                              check=Check.POSITIVE)
    position_min: float = key(-100.0, "lowest allowed position", unit="rad")
    position_max: float = key(100.0, "highest allowed position", unit="rad")
    velocity_limit: float = key(100.0, "largest allowed |velocity| (the drive profile's velocity_limit where lower)",
                                unit="rad/s",
                                check=Check.POSITIVE)
    timing: str = key("feedback", "how the loop is clocked: feedback (each cycle triggered by "
                      "the drive's feedback frame), host (host-clock deadlines; realtime: its old "
                      "name, deprecated, removed in dobhil 0.2) or lockstep (simulated; needs the "
                      "emulator)",
                      choices=("feedback", "host", "lockstep", "realtime"))
    realtime_priority: int = key(0, "SCHED_FIFO priority on Linux (0: none)",
                                 check=Check.NONNEGATIVE, maximum=99)
    spin: float = key(2.0e-4, "spin (instead of sleeping) for this long before each deadline "
                      "(host timing) or around each expected feedback frame (feedback timing); "
                      "0: sleep only", unit="s", check=Check.NONNEGATIVE)
    cpu_affinity: int = key(-1, "pin the control thread to this CPU (-1: no pinning)", minimum=-1)
    mode: str = key("force", "what the reference commands: force (the DOb/RTOb force loop tracks "
                    "it as tau_int^ref) or torque (open loop for identification: the reference is "
                    "the torque command itself, saturated at loop.torque_limit, with every safety "
                    "of a force run; the observers still run and are recorded)",
                    choices=("force", "torque"))


@dataclass(frozen=True)
class ReferenceConfig:
    """The interaction torque reference tau_int^ref of a run (the torque command itself with
    loop.mode: torque)."""

    kind: str = key("step", "reference signal",
                    choices=("step", "ramp", "sine", "chirp", "square", "csv", "prbs",
                             "multisine"))
    amplitude: float = key(1.0, "amplitude (step height, ramp end value, sine amplitude, prbs "
                           "level, multisine peak)", unit="N m")
    offset: float = key(0.0, "value added to the signal", unit="N m")
    start: float = key(0.0, "time the signal starts", unit="s", check=Check.NONNEGATIVE)
    frequency: float = key(1.0, "frequency (sine, square; chirp start; multisine lowest line)",
                           unit="Hz", check=Check.POSITIVE)
    frequency_end: float = key(50.0, "chirp end frequency; multisine highest line", unit="Hz",
                               check=Check.POSITIVE)
    ramp_time: float = key(0.1, "ramp duration", unit="s", check=Check.POSITIVE)
    file: str = key("", "CSV file with columns time,tau_ref (kind csv); a relative path is "
                          "taken from the config file's directory (from the working directory in --set)")
    clock_period: float = key(2.0e-3, "prbs: time each level is held (power flat to about "
                              "0.44 / clock_period, first zero at 1 / clock_period)", unit="s",
                              check=Check.POSITIVE, maximum=1e4)
    lines: int = key(20, "multisine: number of lines, evenly spaced from frequency to "
                     "frequency_end", check=Check.POSITIVE, maximum=10000)
    phases: str = key("schroeder", "multisine phases: schroeder (low crest factor) or random "
                      "(uniform, from reference.seed)", choices=("schroeder", "random"))
    seed: int = key(0, "seed of the prbs levels and of random multisine phases",
                    check=Check.NONNEGATIVE)
    duration: float = key(0.0, "prbs, multisine: how long the excitation lasts after start "
                          "(0: to the end of the run); offset after it", unit="s",
                          check=Check.NONNEGATIVE)


@dataclass(frozen=True)
class SensorConfig:
    """The emulated encoder and velocity estimate."""

    encoder_resolution: int = key(0, "encoder counts per revolution (0: no quantisation)",
                                  check=Check.NONNEGATIVE)
    velocity_noise: float = key(0.0, "standard deviation of the velocity estimate noise",
                                unit="rad/s", check=Check.NONNEGATIVE)
    seed: int = key(0, "seed of the emulator's randomness", check=Check.NONNEGATIVE)


@dataclass(frozen=True)
class DriveConfig:
    """Which drive and which bus."""

    profile: str = key("odrive-0.6", "drive profile under drivers/ (name or path)")
    interface: str = key("", "python-can interface name (empty: the profile's bus; --bus wins)")
    channel: str = key("", "python-can channel (with drive.interface)")
    node_id: int = key(-1, "CAN node id of the drive (-1: the drive profile's node_id); checked "
                       "against the profile's protocol like the profile's own", minimum=-1)
    # the nominal rate: classic CAN and CAN FD's arbitration phase run at most 1 Mbit/s (ISO
    # 11898-1); a CAN FD data phase is the profile's bus.data_bitrate
    bitrate: int = key(1_000_000, "CAN nominal bitrate (0: leave to the interface)", unit="bit/s",
                       check=Check.NONNEGATIVE, maximum=1_000_000)
    latency: float = key(0.0, "emulated bus latency (real-time emulation)", unit="s",
                         check=Check.NONNEGATIVE)
    jitter: float = key(0.0, "emulated bus latency jitter, standard deviation", unit="s",
                        check=Check.NONNEGATIVE)


@dataclass(frozen=True)
class AnalysisConfig:
    """Settings of the analysis, and of the stability gate before a run."""

    step_duration: float = key(0.0, "step response horizon (0: automatic, else at least 1e-6 s)",
                               unit="s", check=Check.NONNEGATIVE, maximum=1e4)
    min_gain_margin: float = key(3.0, "the stability gate of dobhil run, demo and check: one warning line "
                                 "(the run goes on) when the sampled loop's gain margin (how far C_f may "
                                 "be scaled in the exact stable-gain map) is below this; 0: never",
                                 unit="dB", check=Check.NONNEGATIVE, maximum=100.0)
    min_phase_margin: float = key(20.0, "the stability gate of dobhil run, demo and check: one warning line "
                                  "(the run goes on) when the sampled loop's phase margin is below this; "
                                  "0: never", unit="deg", check=Check.NONNEGATIVE, maximum=180.0)


@dataclass(frozen=True)
class InstabilityConfig:
    """The instability watch: a force run that chatters at its torque limit or grows stops."""

    window: float = key(0.5, "the watch's window: each statistic is taken over the last "
                        "window s (rounded to whole loop periods, at least 2); 0: no watch",
                        unit="s", check=Check.NONNEGATIVE, maximum=1e4)
    saturation: float = key(0.12, "chatter rule: the command clipped at the torque limit in at "
                            "least this fraction of the window ...", check=Check.POSITIVE,
                            maximum=1.0)
    limit_reversals: float = key(0.03, "... and turned back from the limit at least this many "
                                 "times per cycle of it (0.03: 15 in 500 cycles)",
                                 check=Check.POSITIVE, maximum=1.0)
    hysteresis: float = key(0.25, "a turn of the command smaller than this fraction of the torque "
                            "limit is not counted (the noise floor of both rules)",
                            check=Check.POSITIVE, maximum=2.0)
    growth: float = key(2.0, "growth rule: the command's oscillation (before the clip) grew by at "
                        "least this factor ...; above 1", check=Check.POSITIVE, maximum=1e6)
    growth_swings: int = key(16, "... over at least this many swings in a row, each larger than the "
                             "one before it in its direction (and at most twice it)", check=Check.POSITIVE,
                             maximum=10000)


@dataclass(frozen=True)
class Config:
    """A complete, validated configuration."""

    plant: PlantConfig = field(default_factory=PlantConfig)
    environment: EnvironmentConfig = field(default_factory=EnvironmentConfig)
    design: DesignConfig = field(default_factory=DesignConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    drive: DriveConfig = field(default_factory=DriveConfig)
    analysis: AnalysisConfig = field(default_factory=AnalysisConfig)
    instability: InstabilityConfig = field(default_factory=InstabilityConfig)

    def flat(self) -> dict[str, Any]:
        """Every key as ``section.name -> value``."""
        return {name: getattr(getattr(self, name.split(".")[0]), name.split(".")[1])
                for name in key_fields()}

    def replace(self, **sections: Any) -> Config:
        return dataclasses.replace(self, **sections)


def _section_types() -> dict[str, type]:
    return {"plant": PlantConfig, "environment": EnvironmentConfig, "design": DesignConfig,
            "loop": LoopConfig, "reference": ReferenceConfig, "sensor": SensorConfig,
            "drive": DriveConfig, "analysis": AnalysisConfig, "instability": InstabilityConfig}


SECTIONS: dict[str, type] = _section_types()


def key_fields() -> dict[str, dataclasses.Field[Any]]:
    """``section.name -> dataclass field`` for every key."""
    return {f"{s}.{f.name}": f for s, cls in SECTIONS.items() for f in dataclasses.fields(cls)}
