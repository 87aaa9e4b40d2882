#!/usr/bin/env python3
"""What recording costs the control loop's thread per cycle, in instructions (valgrind's
callgrind: a count that does not move with the machine's load), against one controller step.

The loop-thread work of ``bench_handover`` in tools/bench.py (one received and one sent frame
through the recording tap, the cycle record, the batches handed to a live writer process),
without its clocks: each side (``plain``: the frames unlogged; ``logged``; ``step``: the demo
configuration's controller step) runs under callgrind at two lengths, and the difference of
the two totals over the difference of the lengths is the side's cost per cycle (start-up,
imports and the writer's start cancel out; the writer process itself is not traced). BLAS
threads and hash seeds are pinned so two runs count alike.

    python tools/loop_log_instructions.py          # prints one JSON object
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: cycles of the two runs of each side (3 records a cycle: whole batches of 128 records)
SHORT, LONG = 1280, 12800
STEPS_SHORT, STEPS_LONG = 2000, 20000


def _side(mode: str, n: int) -> None:
    """Run one side for ``n`` cycles (in the process callgrind traces)."""
    sys.path[:0] = [str(ROOT), str(ROOT / "tools")]
    if mode == "step":
        from bench import load_config  # type: ignore[import-not-found]

        from dobhil.drives.load import load_drive_profile
        from dobhil.runtime.session import build_controller
        config = load_config(ROOT / "configs/demo.yaml")
        step = build_controller(config, load_drive_profile(config)).step
        for _ in range(n):
            step(1e-4, 0.0, 1.0)
        return
    _frames(mode, n)


def _frames(mode: str, n: int) -> None:
    from types import SimpleNamespace

    import can
    from bench import _StubBus  # type: ignore[import-not-found]

    from dobhil.recording.process import WriterProcess
    from dobhil.recording.runlog import RunLog
    from dobhil.runtime.controller import ControlOutput
    with tempfile.TemporaryDirectory() as tmp:
        log = RunLog(WriterProcess(Path(tmp) / "h.mcap", fsync=False))
        log.begin(metadata={}, attachments=[], lossy=False, truth=lambda: (0.0, 0.0, 0.0, 0.0), own_ids={0x069})
        stub = _StubBus()
        bus = stub if mode == "plain" else log.wrap_bus(stub)
        cycle = log.cycle if mode == "logged" else None
        fb = SimpleNamespace(position=1e-4, velocity=0.0, seq=1)
        out = ControlOutput(1.0, 0.99, 0.01, 0.02, 0.03, 0.03)
        cmd = can.Message(arbitration_id=0x06E, data=bytes(4), is_extended_id=False)
        for k in range(n):  # as bench._handover_us, without its clocks
            bus.recv(0.0)
            bus.send(cmd)
            if cycle is not None:
                cycle(k, k * 1e-3, fb, out, 0.0, 3e-5, False)
        log.end("done")
        if log.tap is not None:
            log.tap.shutdown()


def _count(mode: str, n: int) -> int:
    """Instructions of one side's whole process under callgrind."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "callgrind.out"
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
        subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", sys.executable, __file__,
                        "--side", mode, str(n)], env=env, check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        match = re.search(r"^(?:summary|totals): (\d+)", out.read_text(), re.M)
        if match is None:
            raise SystemExit("loop_log_instructions: callgrind wrote no total")
        return int(match.group(1))


def _per_cycle(mode: str, short: int, long: int) -> float:
    return (_count(mode, long) - _count(mode, short)) / (long - short)


def main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[0] == "--side" and argv[1] in ("plain", "logged", "step") and argv[2].isdigit():
        _side(argv[1], int(argv[2]))  # the traced process
        return 0
    if argv:
        print("usage: loop_log_instructions.py (no arguments)", file=sys.stderr)
        return 2
    if shutil.which("valgrind") is None:
        print("loop_log_instructions: valgrind not found (it counts the instructions)", file=sys.stderr)
        return 2
    plain, logged = _per_cycle("plain", SHORT, LONG), _per_cycle("logged", SHORT, LONG)
    step = _per_cycle("step", STEPS_SHORT, STEPS_LONG)
    print(json.dumps({"loop_thread_log_instructions_per_cycle": round(logged - plain),
                      "controller_step_instructions": round(step),
                      "loop_thread_log_cost_vs_controller_step_instructions": round((logged - plain) / step, 3)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
