"""Shipped configs and drive profiles: found by name from any directory, ``dobhil init``,
and the command line's plain help and quiet broken pipe."""

from __future__ import annotations

import errno
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dobhil.cli.main import DESCRIPTION, EXIT_BROKEN_PIPE, main
from dobhil.config import load_config, resolve_config
from dobhil.config.axes import load_axes
from dobhil.data import configs_dir, copy_shipped, drivers_dir, shipped_configs, shipped_profiles
from dobhil.drives.load import load_drive_profile, load_profile
from dobhil.errors import ConfigError, DobhilError

ROOT = Path(__file__).resolve().parents[1]


def _repo_files(top: str) -> list[str]:
    base = ROOT / top
    return sorted(p.relative_to(base).as_posix() for p in base.rglob("*")
                  if p.is_file() and p.name != "__init__.py" and "__pycache__" not in p.parts)


def test_the_shipped_files_are_the_repository_directories() -> None:
    for top, directory in (("configs", configs_dir()), ("drivers", drivers_dir())):
        shipped = sorted(p.relative_to(directory).as_posix() for p in directory.rglob("*")
                         if p.is_file() and p.name != "__init__.py" and "__pycache__" not in p.parts)
        assert shipped == _repo_files(top)
        for rel in shipped:
            assert (directory / rel).read_bytes() == (ROOT / top / rel).read_bytes()
    assert {"demo", "paper/fig2c"} <= set(shipped_configs())
    assert {"odrive-0.5", "odrive-0.6"} <= set(shipped_profiles())


@pytest.mark.parametrize("name", ["demo", "paper/fig2c", "paper/fig3.yaml"])
def test_a_shipped_config_name_works_from_any_directory(name: str, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    stem = name.removesuffix(".yaml")
    assert resolve_config(name) == configs_dir() / f"{stem}.yaml"
    assert load_config(name) == load_config(ROOT / "configs" / f"{stem}.yaml")


def test_a_path_is_always_a_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    Path("demo").write_text("design: {force_gain: 7}\n")  # a local file named like a shipped config
    assert load_config("demo").design.force_gain == 7.0
    with pytest.raises(ConfigError, match="no such file"):
        load_config("configs/demo.yaml")  # not here, and not a name


def test_a_directory_named_like_a_shipped_config_is_no_config(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``dobhil demo --out demo`` makes a folder ``demo``; the next ``dobhil demo`` there said
    "config file demo is a directory, not a file". A folder is never a config: the name is the
    shipped one; a folder of no shipped name is still refused as one."""
    monkeypatch.chdir(tmp_path)
    Path("demo").mkdir()
    Path("mine").mkdir()
    assert resolve_config("demo") == configs_dir() / "demo.yaml"
    with pytest.raises(ConfigError, match="is a directory"):
        load_config("mine")


def test_an_unknown_config_is_one_line_listing_the_shipped_names(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["analyze", "nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "config 'nope'" in err and "demo, paper/fig2a" in err


def test_a_profile_name_works_from_any_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    profile = load_profile("odrive-0.6")
    assert profile.name == "odrive-0.6" and profile.protocol == "odrive"
    with pytest.raises(ConfigError,
                       match=r"drive profile 'nope': expected one of \[.*'epos4', 'mini-cheetah', 'moteus-r4.11', "
                             r"'odrive-0.5', 'odrive-0.6'"):
        load_profile("nope")


def test_init_copies_everything_and_an_edited_profile_is_used(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    dest = tmp_path / "lab"
    assert main(["init", str(dest)]) == 0
    assert "copied" in capsys.readouterr().out
    assert sorted(p.relative_to(dest / "configs").as_posix() for p in (dest / "configs").rglob("*")
                  if p.is_file()) == _repo_files("configs")
    assert sorted(p.relative_to(dest / "drivers").as_posix() for p in (dest / "drivers").rglob("*")
                  if p.is_file()) == _repo_files("drivers")
    # the copy is the user's: a profile name in a copied config finds the edited profile
    profile_file = dest / "drivers" / "odrive-0.6.yaml"
    profile_file.write_text(profile_file.read_text().replace("torque_limit:", "torque_limit: 0.75 #"))
    for config_file in (dest / "configs" / "demo.yaml", dest / "configs" / "paper" / "fig3.yaml"):
        config = load_config(config_file)
        assert load_drive_profile(config, config_file.parent).torque_limit == 0.75
    assert load_drive_profile(load_config("demo"), configs_dir()).torque_limit != 0.75


def test_init_never_overwrites(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dest = tmp_path / "lab"
    (dest / "drivers").mkdir(parents=True)
    mine = dest / "drivers" / "odrive-0.6.yaml"
    mine.write_text("my own\n")
    assert main(["init", str(dest)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "odrive-0.6.yaml exists" in err
    assert mine.read_text() == "my own\n"
    assert not (dest / "configs").exists()  # nothing written when anything would be overwritten
    with pytest.raises(DobhilError, match="not a directory"):
        copy_shipped(mine)


def test_help_is_a_plain_description(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert DESCRIPTION.split()[0] in out and "init" in out
    assert "``" not in out and "Entry point" not in out


def test_a_closed_stdout_is_no_traceback(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "dobhil", "analyze", "paper/fig2c"], cwd=tmp_path,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader went away, as `dobhil ... | head -0` does
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait(timeout=120) == EXIT_BROKEN_PIPE
    assert "Traceback" not in err and "BrokenPipe" not in err, err


FULL = Path("/dev/full")


@pytest.mark.skipif(not FULL.exists(), reason="needs Linux's /dev/full")
@pytest.mark.parametrize("command", [
    ["analyze", "demo"],
    ["analyze", "demo", "--json"],   # json.dump writes to sys.stdout itself
    ["run", "demo", "--emulate", "--lockstep", "--set", "loop.duration=0.05", "--summary-json"],
    ["sweep", "demo", "--vary", "design.force_gain=1:2:3"],
    ["--help"],   # argparse ignores a failed write of its own
])
def test_a_full_stdout_is_one_line_exit_2(tmp_path: Path, command: list[str]) -> None:
    """Standard output on a full device: one line saying so, exit 2 (as a full disk under
    --out), not an internal error (exit 3) nor a help that claims success."""
    with open(FULL, "w") as full:
        done = subprocess.run([sys.executable, "-m", "dobhil", *command], cwd=tmp_path, stdin=subprocess.DEVNULL,
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    prog = "dobhil" if command[0].startswith("-") else f"dobhil {command[0]}"
    assert done.returncode == 2, done.stderr
    lines = done.stderr.splitlines()
    if command[0] == "run":   # a run's stop line gets out on stderr when stdout cannot take it
        assert lines[0].startswith("dobhil run: stopped: done at cycle "), done.stderr
        lines = lines[1:]
    assert lines == [f"{prog}: error: cannot write standard output: No space left on device"], done.stderr


class _FullStream(io.StringIO):
    """A stdout whose every write fails as a full device's does."""

    def write(self, text: str) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("where", ["stdout", "elsewhere"])
def test_a_full_stdout_is_told_from_another_oserror(where: str, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """In process: a failed write to stdout is the environment (exit 2); the same OSError from
    anything else a command does stays what it is, a bug (exit 3)."""
    import dobhil.cli.init_cmd as init_cmd

    def command(args: object) -> int:
        if where == "stdout":
            print("wrote everything")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(init_cmd, "run", command)
    err_stream = sys.stderr
    monkeypatch.setattr(sys, "stdout", _FullStream())
    code = main(["init", "anywhere"])
    assert sys.stderr is err_stream
    err = capsys.readouterr().err
    if where == "stdout":
        assert code == 2 and err == "dobhil init: error: cannot write standard output: No space left on device\n"
    else:
        assert code == 3 and "internal error" in err


def test_a_broken_pipe_that_is_not_stdout_is_not_hidden(monkeypatch: pytest.MonkeyPatch) -> None:
    import dobhil.cli.init_cmd as init_cmd

    def broken(args: object) -> int:
        raise BrokenPipeError(32, "a worker's pipe")

    monkeypatch.setattr(init_cmd, "run", broken)
    with pytest.raises(BrokenPipeError, match="worker"):
        main(["init", "anywhere"])


def test_every_shipped_config_and_profile_loads() -> None:
    """Each shipped config with its drive profile (the CiA 402 demo on cia402-emulated
    too), and each shipped profile by name (epos4, which no config names, too)."""
    assert {"demo", "cia402-demo"} <= set(shipped_configs())
    assert {"cia402-emulated", "epos4"} <= set(shipped_profiles())
    for name in shipped_configs():
        for axis in load_axes(name).axes:   # each axis of a config that lists axes
            config = axis.config
            assert load_drive_profile(config, configs_dir()).name == config.drive.profile   # names, all of them
    for name in shipped_profiles():
        assert load_profile(name).name == name


def test_the_cia402_demo_models_the_sync_latch_and_is_stable_with_it() -> None:
    """configs/cia402-demo.yaml: the protocol applies each command one period after its
    sample (the profile's command_delay_periods), the design models exactly that
    (delay_samples 1, no input_delay), and its gains keep a margin with it -- the file's
    comment claims a largest stable force gain 3.3 times the one it runs."""
    from dobhil.analysis.report import analyze, as_json
    config = load_config("cia402-demo")
    profile = load_drive_profile(config, configs_dir())
    assert profile.protocol == "cia402" and profile.command_delay_periods == 1
    assert config.design.delay_samples == profile.command_delay_periods and config.design.input_delay == 0.0
    sampled = as_json(analyze(config))["discrete"]
    assert sampled["delay_samples"] == 1 and sampled["closed_loop"]["stable"]
    assert sampled["max_stable_force_gain"] >= 3 * config.design.force_gain
    # the demo's own design would keep only a factor 2 with the delay: why the bandwidths differ
    demo_delayed = load_config("demo", ["design.delay_samples=1"])
    tight = as_json(analyze(demo_delayed))["discrete"]["max_stable_force_gain"]
    assert tight < 2.1 * demo_delayed.design.force_gain
