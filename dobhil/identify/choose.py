"""Which identification a log gets: closed loop (:mod:`dobhil.identify.closedloop`) for a
force run of one axis recorded by dobhil, open-loop output error (:mod:`dobhil.identify.fit`) for an
excitation run in torque mode, a CAN log imported, several logs or chosen segments.

Why automatic: a force run's torque depends on the measurement noise through the controller,
and the open-loop fit of it is biased; the closed-loop fit needs the recorded controller and
the whole run from its first cycle, which only a single dobhil run's log has."""

from __future__ import annotations

import os
from typing import Any

from dobhil.errors import ConfigError

__all__ = ["closed_loop_wanted", "recorded_mode", "several_axes"]


def recorded_mode(path: str | os.PathLike[str], axis: str | None = None) -> str | None:
    """``loop.mode`` of a dobhil run's log; None for a log without a config or without loop
    records (a CAN log imported)."""
    from dobhil.recording.axes import axis_log, is_axes_log
    from dobhil.recording.reader import open_log
    with open_log(path) as whole:
        log: Any = axis_log(whole, axis) if axis is not None or is_axes_log(whole) else whole
        if log.config is None or not {"/drive/feedback", "/controller"} <= set(log.topics()):
            return None
        return str(log.config.loop.mode)


def closed_loop_wanted(args: Any) -> bool:
    """True for ``--method closed-loop``, and for ``auto`` on one force run's log without
    ``--segment`` or ``--frf``; ConfigError (one line) when closed loop is asked for what it
    cannot fit. ``--validate`` goes with either: a closed-loop fit is validated by simulating
    the validation run's own loop (:func:`dobhil.identify.closedloop.validate_loop`)."""
    if args.method == "open-loop":
        return False
    # The measured frequency responses are of the torque sent to the motion, the open-loop
    # model's (dobhil/identify/frf.py): they go with the open-loop fit.
    evidence = ["--frf"] if getattr(args, "frf", False) else []
    if evidence and args.method == "closed-loop":
        raise ConfigError("--method closed-loop with --frf: the frequency responses are computed for the "
                          "open-loop fit; use --method open-loop or auto")
    single = len(args.log) == 1 and not args.segment and args.period is None and not evidence
    if args.method == "closed-loop":
        if not single:
            raise ConfigError("--method closed-loop: fits one dobhil run's log as recorded (one LOG, no "
                              "--segment, no --period); use --method open-loop for several logs or segments")
        if several_axes(args.log[0]):
            raise ConfigError(f"--method closed-loop: {args.log[0]} records several axes; the closed-loop fit "
                              "simulates one axis' loop alone, so it takes a one-axis run (use --method open-loop)")
        if recorded_mode(args.log[0], args.axis) is None:
            raise ConfigError(f"--method closed-loop: {args.log[0]} has no recorded controller (a CAN log "
                              "imported?); closed loop needs a run recorded by dobhil, open loop fits this one")
        return True
    return (single and not several_axes(args.log[0])
            and recorded_mode(args.log[0], args.axis) not in (None, "torque"))


def several_axes(path: str | os.PathLike[str]) -> bool:
    """Whether a log records several axes: one axis' closed loop simulated alone would miss
    what the others and their couplings push on it, which the open-loop fit takes in as the
    axis' environment (``dobhil identify --axis``)."""
    from dobhil.recording.axes import is_axes_log
    from dobhil.recording.reader import open_log
    with open_log(path) as log:
        return bool(is_axes_log(log))
