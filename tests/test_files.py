"""Output files: a device, FIFO or special file system is never replaced by a regular file;
a link is written through, not replaced; a recording's name must be UTF-8."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dobhil.files import OutputError, atomic_path, check_new_output, check_output, check_output_dir, input_problem


@pytest.mark.parametrize("target", ["/dev/null", "/dev/stdout", "/proc/self/x.csv", "/sys/x.csv"])
def test_special_file_systems_are_refused(target: str) -> None:
    if not Path(target).parent.exists():
        pytest.skip(f"no {Path(target).parent} here")
    with pytest.raises(OutputError, match="special file system"):
        check_output(target, what="-o")


def test_dev_null_survives_a_refused_export() -> None:
    """As root, the atomic rename over /dev/null used to make it a regular file."""
    if not Path("/dev/null").is_char_device():
        pytest.skip("no /dev/null character device")
    with pytest.raises(OutputError):
        check_output("/dev/null", suffix=".csv")
    assert Path("/dev/null").is_char_device()


def test_a_fifo_is_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "out.csv"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file"):
        check_output(fifo, suffix=".csv")


def test_a_link_is_written_through(tmp_path: Path) -> None:
    real, link = tmp_path / "run42.csv", tmp_path / "latest.csv"
    real.write_text("old\n")
    link.symlink_to(real.name)
    with atomic_path(check_output(link, suffix=".csv")) as tmp:
        tmp.write_text("new\n")
    assert link.is_symlink() and real.read_text() == "new\n"


def test_a_recording_name_that_is_not_utf8_is_refused(tmp_path: Path) -> None:
    name = tmp_path / os.fsdecode(b"run-\xff.mcap")  # what the shell passes for a byte 0xff
    with pytest.raises(OutputError, match=r"run-\\xff.mcap: the file name is not valid UTF-8"):
        check_new_output(name, suffix=".mcap", what="--log")
    assert not name.exists()


def test_a_name_the_system_refuses_is_one_line(tmp_path: Path) -> None:
    """ENAMETOOLONG (and any OSError while looking at the path) is an OutputError, not a traceback."""
    with pytest.raises(OutputError, match="File name too long") as info:
        check_output(tmp_path / ("x" * 300 + ".png"), what="--plot")
    assert "\n" not in str(info.value)
    with pytest.raises(OutputError, match="too long"):
        check_output_dir(tmp_path / ("d" * 300), ["a.png"], what="--plot")


def test_an_output_directory_is_checked_for_every_file(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        check_output_dir(tmp_path / "file", ["a.png"], what="--plot")
    with pytest.raises(OutputError, match="not a directory"):
        check_output_dir(tmp_path / "file" / "sub", ["a.png"], what="--plot")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "b.png").mkdir()
    with pytest.raises(OutputError, match="is a directory"):
        check_output_dir(tmp_path / "out", ["a.png", "b.png"], what="--plot")
    assert check_output_dir(tmp_path / "new" / "deeper", ["a.png"]) == tmp_path / "new" / "deeper"


def test_input_problem_names_what_the_path_is(tmp_path: Path) -> None:
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    (tmp_path / "ok").write_text("x")
    assert input_problem(tmp_path / "missing") == "no such file"
    assert "directory" in str(input_problem(tmp_path))
    assert "FIFO" in str(input_problem(fifo))
    assert input_problem(tmp_path / "ok") is None
    assert "too long" in str(input_problem(tmp_path / ("x" * 300)))


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_unwritable_output_directory_is_refused(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    with pytest.raises(OutputError, match="not writable"):
        check_output_dir(locked / "plots", ["a.png"], what="--plot")


def test_a_loop_of_symbolic_links_is_one_line(tmp_path: Path) -> None:
    """ELOOP (Path.resolve raises RuntimeError for it) as an output, an input and a directory."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(OutputError, match="loop of symbolic links"):
        check_output(tmp_path / "a", what="--out")
    with pytest.raises(OutputError, match="loop of symbolic links"):
        check_output_dir(tmp_path / "a", ["x.png"], what="--plot")
    assert check_output(tmp_path / "fine.csv", inputs=[tmp_path / "a"]) == tmp_path / "fine.csv"
    assert "symbolic links" in str(input_problem(tmp_path / "a"))
