"""Two dobhil runs on one vcan, each with an emulator process of its own: ODrive node 3 and
ODrive node 4 -- the same protocol, so the same commands and feedback layouts at ids 32 apart,
where only the node id filters keep them apart. Both converge; neither reacts to the other's
frames, shown from what each left behind: ``candump -l``'s log of the whole bus, each run's
MCAP and each emulator's counts."""

from __future__ import annotations

import time
from pathlib import Path


from dobhil.drives.decode import decode_motion
from dobhil.drives.odrive import codec
from dobhil.drives.load import load_profile

from .guest import CONFIGS, START_TIMEOUT, Dobhil, Dumped, Proc, guest_overlay, summary_json
from .peers import crashes_say_where  # noqa: F401 (an autouse fixture: applies here)
from .peers import EmulatorCounts, Recorded, candump_log, emulator_counts, read_candump, read_run, start_candump

#: per node: its own plant start and force reference, so that no frame of one run could pass
#: for the other's (a run fed the other's feedback, or an emulator the other's torque, shows)
RUNS = {3: {"plant.initial_position": -0.005, "reference.offset": 0.2, "reference.amplitude": 0.8},
        4: {"plant.initial_position": -0.004, "reference.offset": 0.5, "reference.amplitude": -0.2}}
#: long enough that the two runs overlap whichever starts first (a process starts in ~8 s
#: under TCG); the overlap is measured from the logs, not assumed
SECONDS = 8.0
#: four real-time processes share the guest's two emulated processors: half the rate of a
#: single pair (tests/socketcan/guest.py's), with observers to match (the demo's sampled
#: loop at 20 ms, 20 rad/s: stable up to C_f = 5.9 for its 2, ``dobhil analyze``)
RATE = {"loop.period": 0.02, "loop.feedback_timeout": 0.2, "design.dob_bandwidth": 20.0,
        "design.rtob_bandwidth": 20.0}


def _node(arbitration_id: int) -> int:
    return codec.split_id(arbitration_id)[0]


def _check_run(node: int, rec: Recorded, profile: str, other_profile: str, proc: Proc) -> int:
    """The run converged, sent only to its node, and every cycle's feedback is one of its
    own node's encoder frames, none of the other's -- though its /can/rx holds the other's
    frames. Returns how many of those it recorded."""
    summary = summary_json(proc)
    assert summary["stop_reason"] == "done" and summary["drive_disabled"] is True, proc.text()
    final = summary["final"]
    assert abs(final["tau_int_hat"] - final["tau_ref"]) < 0.03 * abs(final["tau_ref"]), final
    expected = RUNS[node]["reference.offset"] + RUNS[node]["reference.amplitude"]
    assert abs(final["tau_ref"] - expected) < 1e-9, final
    assert {_node(m.arbitration_id) for m in rec.frames("/can/tx")} == {node}
    rx = rec.frames("/can/rx")
    other = [m for m in rx if _node(m.arbitration_id) != node]
    assert other and {_node(m.arbitration_id) for m in other} == {7 - node}, "the other run's frames"
    own = {(p, v) for _, p, v in decode_motion(load_profile(profile), rx)}
    theirs = {(p, v) for _, p, v in decode_motion(load_profile(other_profile), rx)}
    seen = {(f["position"], f["velocity"]) for f in rec.topic("/drive/feedback")}
    assert seen <= own and not seen & theirs, f"node {node}: feedback from the other node"
    losses = [e for e in rec.topic("/events") if e["kind"] == "loss"]
    assert all("foreign" in e["reason"] for e in losses), losses
    return len(other)


def _check_emulator(node: int, counts: EmulatorCounts, dumped: list[Dumped], outer: bool) -> None:
    """The emulator's own counts against candump's log of the bus. What it took as addressed
    is exactly what others sent to its node (all its node's frames on the bus but the ones it
    sent itself); every frame of the other node it read was not addressed to it. The
    emulator started first and stopped last read all of those; the other, started later and
    stopped first, at least those between its first frame and its second-to-last encoder
    estimate (its socket was open, and its thread had read them before that tick's step)."""
    assert counts.node == node
    mine = [f for f in dumped if _node(f.arbitration_id) == node]
    theirs = [f for f in dumped if _node(f.arbitration_id) == 7 - node]
    assert counts.received - counts.not_addressed == len(mine) - counts.sent, counts
    if outer:
        assert counts.not_addressed == len(theirs), (counts, len(theirs))
        return
    encoder = codec.arbitration_id(node, codec.CmdId.GET_ENCODER_ESTIMATES)
    first, before = mine[0].stamp, [f.stamp for f in mine if f.arbitration_id == encoder][-2]
    assert sum(first < f.stamp < before for f in theirs) <= counts.not_addressed <= len(theirs), counts


def test_two_runs_on_one_vcan_keep_to_their_own_nodes(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    config = CONFIGS / "demo.yaml"
    overlays = {node: guest_overlay(tmp_path, "odrive", extra={**sets, **RATE, "loop.duration": SECONDS},
                                    profile={"node_id": node, "feedback_period": RATE["loop.period"]})
                for node, sets in RUNS.items()}
    profiles = {node: str(yaml_value(path, "drive.profile")) for node, path in overlays.items()}
    dump = start_candump(dobhil, vcan)
    emulators = {node: dobhil.emulate(config, vcan, overlays[node]) for node in RUNS}
    logs = {node: tmp_path / f"run-{node}.mcap" for node in RUNS}
    runs = {node: dobhil.start(f"run-{node}", ["run", str(config), "--bus", f"socketcan:{vcan}", "--set-file",
                                               str(overlays[node]), "--log", str(logs[node]), "--summary-json"])
            for node in RUNS}
    for proc in runs.values():
        proc.wait(4 * START_TIMEOUT)
    # node 4's emulator first: node 3's reads on until node 4's last frame, then stops too
    emulators[4].stop()
    time.sleep(1.0)
    emulators[3].stop()
    dump.stop()

    dumped = read_candump(candump_log(dobhil))
    frames = {node: sum(1 for f in dumped if _node(f.arbitration_id) == node) for node in RUNS}
    assert sum(frames.values()) == len(dumped)   # nothing else on the bus
    records = {node: read_run(logs[node], ("/can/rx", "/can/tx", "/drive/feedback", "/events", "/loop"))
               for node in RUNS}
    foreign = {node: _check_run(node, records[node], profiles[node], profiles[7 - node], runs[node]) for node in RUNS}
    for node in RUNS:
        _check_emulator(node, emulator_counts(emulators[node]), dumped, outer=node == 3)
    spans = {node: (records[node].timed("/loop")[0][0], records[node].timed("/loop")[-1][0]) for node in RUNS}
    overlap = (min(s[1] for s in spans.values()) - max(s[0] for s in spans.values())) / 1e9
    assert overlap > 0, spans
    print(f"loops overlapped {overlap:.2f} s; bus frames by node {frames}; foreign frames recorded {foreign}; "
          f"emulators {[emulator_counts(e) for e in emulators.values()]}")


def yaml_value(path: Path, key: str) -> object:
    import yaml
    return yaml.safe_load(path.read_text(encoding="utf-8"))[key]
