"""The whole identify workflow, end to end, through the CLI:

1. excite: ``dobhil run identify-free`` and ``identify-contact`` on the emulator (lockstep:
   reproducible) with what a real rig has switched on -- Coulomb friction, a quantising
   encoder, velocity noise and a fractional input delay;
2. identify: ``dobhil identify free.mcap contact.mcap --out overlay.yaml`` (one fit of both:
   the free run's friction, the contact run's environment);
3. re-run: the force config (``demo``) on the identified plant (``--set-file overlay.yaml``)
   against the same run on the true plant: ``dobhil compare`` must find them closer than two
   runs of the true plant with different noise seeds are to each other -- and a run on the
   plant one would have assumed without identify (the config's, no Coulomb friction, no
   delay) must not be (the control that lets the check fail);
4. the same numbers from the runs' frames alone: written to .blf / .asc with python-can's own
   writers and read back with ``dobhil log import``.

The true plant is read from the shipped configs plus :data:`TRUE_SETS`, never typed here.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import can_frame_message

#: what makes the emulated plant a real one's likeness (the issue's "sensor quantisation, noise
#: and Coulomb friction on"), plus a fractional delay so the delay has something to find: a 20 bit
#: encoder (6 urad a count: a contact's whole travel here is some 25 counts), 1 mrad/s velocity noise
TRUE_SETS = ("plant.coulomb_friction=0.05", "sensor.encoder_resolution=1048576", "sensor.velocity_noise=0.001",
             "design.input_delay=0.0004")
#: the plant keys an overlay may set, with the identified parameter's name
PLANT_KEYS = {"plant.inertia": "inertia", "plant.viscous_friction": "viscous_friction",
              "plant.coulomb_friction": "coulomb_friction", "environment.stiffness": "stiffness",
              "environment.damping": "damping", "environment.contact_position": "contact_position"}
FREE_SECONDS, CONTACT_SECONDS = 3.0, 2.0


def _sets(*items: str) -> list[str]:
    return [a for item in items for a in ("--set", item)]


def _run(config: str, log: Path, *extra: str) -> Path:
    """``dobhil run CONFIG --emulate --lockstep --log LOG`` with ``extra`` arguments."""
    assert main(["run", config, "--emulate", "--lockstep", "--log", str(log), *extra]) == 0
    return log


def _identify(capsys: pytest.CaptureFixture[str], *args: str) -> dict[str, Any]:
    capsys.readouterr()
    assert main(["identify", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)  # type: ignore[no-any-return]


def _truth() -> dict[str, float]:
    """The emulated plant's parameters, from the shipped configs with TRUE_SETS."""
    free, contact = load_config("identify-free", TRUE_SETS), load_config("identify-contact", TRUE_SETS)
    import dataclasses
    same = dataclasses.replace(free.plant, initial_position=contact.plant.initial_position)
    assert same == contact.plant and free.design.input_delay == contact.design.input_delay   # one servo
    d = contact.design
    return {"inertia": contact.plant.inertia, "viscous_friction": contact.plant.viscous_friction,
            "coulomb_friction": contact.plant.coulomb_friction, "stiffness": contact.environment.stiffness,
            "damping": contact.environment.damping, "contact_position": contact.environment.contact_position,
            "delay": d.delay_samples * contact.loop.period + d.input_delay}


@pytest.fixture(scope="module")
def workflow(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Steps 1 and 2: the two excitation logs, the overlay and the identification's JSON
    (``info``: what that one fit printed, so the test of its numbers need not fit again);
    ``contact_alone``: the contact log's own fit over its whole run, which each imported
    copy of its frames is compared with."""
    d = tmp_path_factory.mktemp("workflow")
    free = _run("identify-free", d / "free.mcap", *_sets(*TRUE_SETS, "sensor.seed=1", f"loop.duration={FREE_SECONDS}"))
    contact = _run("identify-contact", d / "contact.mcap",
                   *_sets(*TRUE_SETS, "sensor.seed=2", f"loop.duration={CONTACT_SECONDS}"))
    overlay = d / "overlay.yaml"
    info = _printed_json(["identify", str(free), str(contact), "--out", str(overlay), "--json"])
    contact_alone = _printed_json(["identify", str(contact), "--segment", f"0:{CONTACT_SECONDS}:contact", "--json"])
    return {"dir": d, "free": free, "contact": contact, "overlay": overlay, "info": info,
            "contact_alone": contact_alone}


def _printed_json(argv: list[str]) -> dict[str, Any]:
    """The JSON ``dobhil ARGV`` prints (a module fixture has no capsys: its stdout is caught here)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    return json.loads(out.getvalue())  # type: ignore[no-any-return]


def test_identify_recovers_the_shipped_configs_plant(workflow: dict[str, Any]) -> None:
    """Both shipped excitations, fitted together: each log's one segment found, the issue's
    accuracy where it sets one, every other number's interval around the truth, no misfit."""
    info = workflow["info"]
    assert [(s["file"], s["kind"]) for s in info["segments"]] == [("free.mcap", "free"), ("contact.mcap", "contact")]
    assert info["segments"][0]["t1"] == pytest.approx(FREE_SECONDS)
    assert info["segments"][1]["t1"] == pytest.approx(CONTACT_SECONDS)
    e, truth = info["estimates"], _truth()
    assert not info["residual"]["warning"], info["residual"]
    for name in ("inertia", "viscous_friction", "coulomb_friction", "stiffness", "damping", "delay"):
        assert e[name]["identifiable"], (name, e[name])
    assert e["inertia"]["value"] == pytest.approx(truth["inertia"], rel=0.02)
    assert e["stiffness"]["value"] == pytest.approx(truth["stiffness"], rel=0.02)
    assert e["damping"]["value"] == pytest.approx(truth["damping"], rel=0.10)
    assert e["delay"]["value"] == pytest.approx(truth["delay"], abs=0.05e-3)
    # the friction of this servo (b = 0.02: 2e-3 N m at the run's 0.1 rad/s) has no target in the
    # issue; its error must be the noise's (the 95 % intervals' coverage is tests/identify/test_fit.py's)
    for name in ("viscous_friction", "coulomb_friction"):
        assert abs(e[name]["value"] - truth[name]) <= 3.0 * e[name]["stderr"], (name, truth[name], e[name])
    if e["contact_position"]["identifiable"]:   # a position is known to an encoder count
        count = 2 * math.pi / load_config("identify-contact", TRUE_SETS).sensor.encoder_resolution
        assert e["contact_position"]["value"] == pytest.approx(truth["contact_position"], abs=count)
    overlay = yaml.safe_load(workflow["overlay"].read_text(encoding="utf-8"))
    for key, name in PLANT_KEYS.items():
        assert (key in overlay) == e[name]["identifiable"], key
        if key in overlay:
            assert overlay[key] == pytest.approx(e[name]["value"], rel=1e-12)


def _force_run(workflow: dict[str, Any], name: str, seed: int, *extra: str) -> Path:
    """A run of the force config ``demo`` at noise seed ``seed``: on the true plant (``extra``
    empty) or another one."""
    return _run("demo", workflow["dir"] / f"{name}.mcap", *extra,
                *_sets("sensor.encoder_resolution=1048576", "sensor.velocity_noise=0.001", f"sensor.seed={seed}"))


def _compare(capsys: pytest.CaptureFixture[str], a: Path, b: Path) -> float:
    capsys.readouterr()
    assert main(["compare", str(a), str(b), "--json"]) == 0
    return float(json.loads(capsys.readouterr().out)["rms"])


def test_rerun_with_the_identified_plant_matches_within_the_noise(workflow: dict[str, Any],
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The identified plant responds like the true one, to within the noise: the force
    difference of the same run (same noise seed) on the two plants is below the difference the
    noise alone makes between two runs of the true plant. The overlay is applied as a user
    would, except the design's inertia (the overlay proposes the identified one; the check is
    of the plant, so the controller stays the run's own)."""
    true_plant = _sets(*TRUE_SETS[:1], *TRUE_SETS[3:])
    keep_design = _sets(f"design.identified_inertia={load_config('demo').design.identified_inertia}")
    a = _force_run(workflow, "a", 1, *true_plant)
    noise = _compare(capsys, a, _force_run(workflow, "a2", 2, *true_plant))
    identified = _compare(capsys, a, _force_run(workflow, "b", 1, "--set-file", str(workflow["overlay"]),
                                                *keep_design))
    assumed = _compare(capsys, a, _force_run(workflow, "c", 1))   # the config's plant: no Coulomb, no delay
    assert math.isfinite(noise) and noise > 0.0
    assert identified < noise < assumed, (identified, noise, assumed)


def _frames(log: Path) -> list[can.Message]:
    with open_log(log) as f:
        frames = [can_frame_message(p, t) for _, t, p in f.iter_messages(("/can/rx", "/can/tx"))]
    return sorted(frames, key=lambda m: m.timestamp)


def _imported(log: Path, suffix: str, direction: str | None = None) -> Path:
    """``log``'s CAN frames written by python-can's writer for ``suffix`` (.blf, .asc, .log),
    then ``dobhil log import``-ed: a frames-only MCAP. A .log's direction can be made one for
    all frames: ``""`` is what ``candump -l`` writes (its log format has none, can-utils
    ``lib.c``: every frame reads back as received, the host's commands included), ``" T"``
    what python-can's logger writes for a capture of vcan (SocketCAN's ``is_rx`` is False for
    every frame made on the machine: every frame is sent, the drive's feedback included)."""
    canlog = log.with_name(log.stem + suffix)
    with can.Logger(str(canlog)) as writer:
        for msg in _frames(log):
            writer.on_message_received(msg)
    if direction is not None:
        lines = canlog.read_text(encoding="ascii").splitlines()
        canlog.write_text("".join(line.removesuffix(" R").removesuffix(" T") + direction + "\n" for line in lines),
                          encoding="ascii")
    tag = "" if direction is None else "-" + (direction.strip() or "none")
    out = log.with_name(f"{log.stem}-{suffix[1:]}{tag}.mcap")
    assert main(["log", "import", str(canlog), "-o", str(out)]) == 0
    return out


@pytest.mark.parametrize(("suffix", "direction"), [(".blf", None), (".log", ""), (".log", " T")],
                         ids=["blf", "candump", "all-sent"])
def test_imported_can_logs_identify_like_the_mcap(workflow: dict[str, Any], suffix: str, direction: str | None,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The contact run's frames alone (.blf; .log as candump writes it, no direction, or with
    every frame sent): the same numbers as its loop records, once the segment is the same
    samples (motion frame 0 is the feedback before cycle 0: cycle k is frame k + 1). And the
    .asc of the free run decodes to the loop records' samples."""
    from dobhil.drives.load import load_profile
    from dobhil.identify.data import read_log
    seconds = CONTACT_SECONDS
    mcap = workflow["contact_alone"]
    imported = _imported(workflow["contact"], suffix, direction)
    frames = _identify(capsys, str(imported), "--drive", "odrive-0.6", "--period", "0.001",
                       "--segment", f"0.001:{seconds + 0.001}:contact")
    for name, e in mcap["estimates"].items():
        f = frames["estimates"][name]
        assert f["identifiable"] == e["identifiable"], name
        if e["identifiable"]:
            assert f["value"] == pytest.approx(e["value"], rel=1e-6), name
            assert f["stderr"] == pytest.approx(e["stderr"], rel=1e-3), name
    if direction is not None:
        return
    loop = read_log(workflow["free"])
    asc = read_log(_imported(workflow["free"], ".asc"), profile=load_profile("odrive-0.6"), period=1e-3)
    n = loop.samples
    assert (asc.position[1:n + 1] == loop.position).all() and (asc.velocity[1:n + 1] == loop.velocity).all()
    assert abs(asc.torque[1:n] - loop.torque[:-1]).max() <= 1e-6   # the drive's float32 field


def test_backlash_shows_as_a_misfit_when_the_contact_opens(workflow: dict[str, Any],
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Gear backlash is invisible while the servo stays pressed (the record is the linear model
    with the contact half the dead band further in), but a contact that opens and closes again
    crosses the dead band each time: identify-contact with the torque dipping below zero
    (offset 0.3 +- 0.5 N m) gives the misfit warning with 50 urad of backlash, and the same
    record of the plant without backlash (the control) none. The free runs between the
    touches belong to one contact segment (the model switches in and out itself)."""
    leave = (*TRUE_SETS, "sensor.seed=3", "loop.duration=1", "reference.offset=0.3")
    infos = {}
    for backlash in (0.0, 5e-5):
        log = _run("identify-contact", workflow["dir"] / f"backlash-{backlash:g}.mcap",
                   *_sets(*leave, f"plant.backlash={backlash}"))
        infos[backlash] = _identify(capsys, str(log))
        assert [s["kind"] for s in infos[backlash]["segments"]] == ["contact"]
    assert not infos[0.0]["residual"]["misfit"], infos[0.0]["residual"]
    assert infos[5e-5]["residual"]["misfit"] and "misfit" in infos[5e-5]["residual"]["warning"]
