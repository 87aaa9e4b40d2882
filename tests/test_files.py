"""Output files: a device, FIFO or special file system is never replaced by a regular file;
a link is written through, not replaced; a recording's name must be UTF-8."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dobhil.files import OutputError, atomic_path, check_new_output, check_output


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
