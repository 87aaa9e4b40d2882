"""An output never overwrites a file the command reads: not only its config and --set-file
overlays, but the files the config names (a csv reference, a drive profile) and the overlays
of --uncertainty-from and --draw-from (dobhil/cli/common.py, ``files_read``)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from dobhil.cli.common import files_read
from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.data import drivers_dir

CSV = "time,tau_ref\n0,0.2\n0.1,0.5\n"


def _refused(args: list[str], kept: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = kept.read_bytes()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.endswith(f"{kept}: is an input of this command; refusing to overwrite it\n"), err
    assert kept.read_bytes() == before


def test_sweep_spares_the_reference_it_reads_and_replay_takes_none(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A replay reads no reference file (its references are the recording's): a --set of one
    is refused as a key the replay does not apply, and the file is left as it was."""
    csv = tmp_path / "ref.csv"
    csv.write_text(CSV)
    uses = ["--set", "reference.kind=csv", "--set", f"reference.file={csv}"]
    _refused(["sweep", "demo", "--vary", "design.force_gain=1:2:2", *uses, "--out", str(csv)], csv, capsys)
    log = tmp_path / "run.mcap"
    assert main(["run", "demo", "--emulate", "--lockstep", "--set", "loop.duration=0.05", "--log", str(log)]) == 0
    capsys.readouterr()
    assert main(["replay", str(log), *uses, "--out", str(csv)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--set reference.kind=csv: a replay re-runs the recorded controller" in err, err
    assert csv.read_text() == CSV


def test_tune_spares_the_drive_profile_it_reads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    profile = tmp_path / "my-odrive.yaml"
    profile.write_bytes((drivers_dir() / "odrive-0.6.yaml").read_bytes())
    _refused(["tune", "demo", "--range", "environment.stiffness=1e3:1e5", "--set", f"drive.profile={profile}",
              "--out", str(profile)], profile, capsys)


def test_files_read_names_every_input(tmp_path: Path) -> None:
    """Relative names the config gives are looked for beside it, as the run does, and as given."""
    config = tmp_path / "c.yaml"
    config.write_text("reference:\n  kind: csv\n  file: ref.csv\ndrive:\n  profile: p.yaml\n")
    args = argparse.Namespace(config=str(config), set_files=["o.yaml"], uncertainty_from="u.yaml",
                              draw_from=None, overrides=[])
    found = files_read(load_config(str(config), [], []), args)
    assert set(found) == {config, Path("o.yaml"), Path("u.yaml"), Path("ref.csv"), tmp_path / "ref.csv",
                          Path("p.yaml"), tmp_path / "p.yaml"}
