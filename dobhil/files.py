"""Output files that never destroy an input and never leave half a file.

Every command that writes checks its outputs before it starts (:func:`check_output`: not
one of its inputs after resolving links, not a directory, in a writable place, the right
suffix) and writes through :func:`atomic_path`: a temporary name in the same directory,
renamed over the target only when the output is complete.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from dobhil.errors import DobhilError


class OutputError(DobhilError, ValueError):
    """An output path that cannot or must not be written."""


#: top-level directories of Linux's special file systems: nothing there is an output file
#: (/dev/stdout is a link to /proc/self/fd/1; the atomic rename would replace a device);
#: /dev/shm, a RAM disk of ordinary files, is allowed
_SPECIAL = ("dev", "proc", "sys")


def shown(path: str | os.PathLike[str]) -> str:
    """``path`` as text that can be printed and written: bytes of a name that are not UTF-8
    (lone surrogates to Python) as ``\\xff`` escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether ``a`` and ``b`` name one existing file (a link, another spelling of the path);
    False where either is missing or cannot be looked at."""
    try:
        return os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str]] = (),
                 suffix: str | Iterable[str] | None = None, what: str = "output", new: bool = False) -> Path:
    """``path`` if it can be written; :class:`OutputError` (one line) if not (also when the
    system refuses to look at it: a name too long, a loop of links, no permission)."""
    try:
        return _check_output(Path(path), list(inputs), suffix, what, new)
    except OutputError:
        raise
    except (OSError, RuntimeError) as exc:  # RuntimeError: Path.resolve() in a loop of symbolic links
        why = getattr(exc, "strerror", None) or ("a loop of symbolic links" if isinstance(exc, RuntimeError)
                                                 else type(exc).__name__)
        raise OutputError(f"{what} {shown(path)}: not a usable file name ({why})") from None


def check_output_dir(path: str | os.PathLike[str], names: Iterable[str], *,
                     inputs: Iterable[str | os.PathLike[str]] = (), what: str = "output") -> Path:
    """Directory ``path`` (created later if missing) if each of ``names`` can be written in it."""
    p = Path(path)
    try:
        is_other = p.exists() and not p.is_dir()
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise OutputError(f"{what} {shown(path)}: not a usable directory name ({why})") from None
    if is_other:
        raise OutputError(f"{what} {p}: exists and is not a directory; give a directory")
    for name in names:
        check_output(p / name, inputs=inputs, what=what)
    return p


def _check_output(p: Path, inputs: list[str | os.PathLike[str]], suffix: str | Iterable[str] | None,
                  what: str, new: bool) -> Path:
    p.resolve()  # raises for a loop of symbolic links (and a name the system refuses)
    for source in inputs:
        try:
            resolved = Path(source).resolve()
        except (OSError, RuntimeError):  # an unusable input: its own check says so
            continue
        if same_file(p, source) or p.resolve() == resolved:
            raise OutputError(f"{what} {p}: is an input of this command; refusing to overwrite it")
    suffixes = (suffix,) if isinstance(suffix, str) else tuple(suffix or ())
    if suffixes and p.suffix.lower() not in suffixes:
        raise OutputError(f"{what} {p}: expected a {' or '.join(suffixes)} file name")
    if p.is_dir():
        raise OutputError(f"{what} {p}: is a directory")
    for where in (Path(os.path.abspath(p)), Path(os.path.realpath(p))):  # as given, and its link's end
        if len(where.parts) > 1 and where.parts[1] in _SPECIAL and where.parts[1:3] != ("dev", "shm"):
            raise OutputError(f"{what} {p}: is in /{where.parts[1]} (a special file system: devices, "
                              "processes); dobhil writes whole files: give a file name")
    if p.exists() and not p.is_file():
        # a device (/dev/null, /dev/stdout), FIFO or socket: the atomic rename would put a
        # regular file in its place (as root, /dev/null itself)
        raise OutputError(f"{what} {p}: is not a regular file (a device, FIFO or socket); "
                          "dobhil writes whole files: give a file name")
    if new and p.exists():
        raise OutputError(f"{what} {p}: exists; refusing to overwrite a recording")
    parent = next(d for d in (p.absolute().parent, *p.absolute().parents) if d.exists())
    if not parent.is_dir():
        raise OutputError(f"{what} {p}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise OutputError(f"{what} {p}: not writable (permissions or a read-only file system)")
    return p


def check_new_output(path: str | os.PathLike[str], *, suffix: str, what: str) -> Path:
    """:func:`check_output` for a file that must not exist yet (a recording).

    A recording stores its own name (UTF-8 metadata), so a name that is not valid UTF-8
    (a byte such as 0xff from the shell, a lone surrogate to Python) is refused here,
    before the run, rather than failing the recorder mid-run."""
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        raise OutputError(f"{what} {shown(path)}: the file name is not valid UTF-8; choose another name") from None
    return check_output(path, suffix=suffix, what=what, new=True)


def input_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` cannot be read as an input file (one phrase), or None if it is a regular file."""
    p = Path(path)
    try:
        info = p.stat()
    except FileNotFoundError:
        return "no such file"
    except OSError as exc:
        return f"cannot be read ({exc.strerror or type(exc).__name__})"
    if stat.S_ISDIR(info.st_mode):
        return "is a directory, not a file"
    if not stat.S_ISREG(info.st_mode):
        return "is not a regular file (a FIFO, socket or device)"
    return None


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path next to ``path`` (same suffix) to write; renamed to ``path`` when the
    block ends normally, removed when it raises."""
    target = Path(path)
    if target.is_symlink():  # write through the link: the rename must not replace the link itself
        target = Path(os.path.realpath(target))
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.stem}.{os.getpid()}.partial{target.suffix}")
    try:
        yield tmp
        os.replace(tmp, target)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{target}: cannot write: {exc.strerror or exc}") from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


__all__ = ["OutputError", "atomic_path", "check_new_output", "check_output", "check_output_dir", "input_problem",
           "shown"]
