"""dobhil.errors.exception_line: any exception as one line for a message."""

from __future__ import annotations

import keyword

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.errors import BusError, exception_line

#: class names an exception can have: identifiers (what ``class`` accepts), keywords aside
names = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,20}", fullmatch=True).filter(
    lambda n: not keyword.iskeyword(n))


def _raised(name: str, text: str) -> Exception:
    return type(name, (Exception,), {})(text)


@given(name=names, text=st.text())
def test_any_text_is_one_line_with_its_type(name: str, text: str) -> None:
    line = exception_line(_raised(name, text))
    assert len(line.splitlines()) == 1          # every line break of str.splitlines folded
    assert line == line.strip() and "  " not in line
    assert line.split(":")[0] == name           # the type's name leads
    words = text.split()
    assert line == (f"{name}: {' '.join(words)}" if words else name)


@given(name=names, text=st.text())
def test_unnamed_keeps_the_text_alone_or_the_name(name: str, text: str) -> None:
    line = exception_line(_raised(name, text), named=False)
    assert len(line.splitlines()) == 1
    assert line == (" ".join(text.split()) or name)


def test_a_failing_str_gives_the_type_name() -> None:
    class Broken(Exception):
        def __str__(self) -> str:
            raise RuntimeError("no text")

    assert exception_line(Broken()) == "Broken"


@pytest.mark.parametrize(("exc", "line"), [
    (KeyError("axis"), "KeyError: 'axis'"),
    (BusError("bus read failed:\n  socket\tclosed\r\n"), "BusError: bus read failed: socket closed"),
    (ValueError(), "ValueError"),
    (OSError(5, "Input/output error"), "OSError: [Errno 5] Input/output error"),
])
def test_literal_lines(exc: BaseException, line: str) -> None:
    assert exception_line(exc) == line
