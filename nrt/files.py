"""Writing files safely: names that stay inside their folder, folders that can take files,
atomic replacement, and write failures as one clear error.

- :func:`check_name`: a config value that becomes a path component (``scene.name``,
  ``stage.name``) holds only the characters of :data:`NAME_CHARS`, so that nothing is
  written outside the output folder;
- :func:`check_output_folder`: a folder nrt is about to create files in is a folder (or can
  be created) and is writable, checked before any data is loaded;
- :func:`atomic_write`: a file is written to a temporary sibling and renamed over its
  target, so a reader (or a resumed run) sees the old file or the new one, never half of one;
- :func:`writing`: an ``OSError`` (a full disk, a read-only or vanished folder) while
  writing becomes a :class:`~nrt.errors.WriteError` naming what was written and where.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from nrt.errors import ConfigError, NrtError, WriteError

NAME_CHARS = "letters, digits, '_', '-', '.' and '+', not starting with '.' or '-'"
"""The characters a name that becomes a folder or file name may hold (in words)."""

_NAME = re.compile(r"[A-Za-z0-9_+][A-Za-z0-9_.+-]{0,127}")

TEMP_MARK = ".partial-"
"""In the name of a temporary file or folder that is renamed into place once complete."""

SPACE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def check_name(key: str, value: object, error: type[NrtError] = ConfigError) -> str:
    """``value`` as a path component, or ``error`` naming ``key``: a name with a path
    separator, ``..``, or a character outside :data:`NAME_CHARS` could write outside the
    output folder (``scene.name=../../x``)."""
    name = str(value)
    if not _NAME.fullmatch(name):
        raise error(f"{key}={value!r}: a name that becomes a folder name may hold only "
                    f"{NAME_CHARS} (at most 128), so that nothing is written outside the "
                    "output folder. Choose another name; to train on a dataset elsewhere, "
                    "pass scene.path=<folder> with a plain scene.name.")
    return name


def check_output_folder(folder: str | Path, key: str) -> None:
    """Refuse a folder (named by the config key ``key``) that nrt cannot create files in:
    it, or the nearest part of its path that exists, is a file, or is not writable."""
    path = Path(os.path.abspath(Path(folder).expanduser()))
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(f"{key}: '{existing}' is a file, not a folder, so '{path}' cannot "
                          f"be created. Point {key} at a folder (or at a path that does not "
                          "exist yet), or move the file away.")
    if not os.access(existing, os.W_OK | os.X_OK):
        made = "" if existing == path else f", where '{path}' would be created,"
        raise ConfigError(f"{key}: the folder '{existing}'{made} is not writable by this "
                          f"user. Point {key} at a writable folder, or change its permissions.")


def _message(what: str, path: Path, exc: OSError) -> str:
    reason = exc.strerror or str(exc)
    if exc.errno in SPACE_ERRORS:
        advice = "Free space on that disk (or point paths.output_dir at another one)"
    else:
        advice = "Check that the folder exists and is writable"
    return f"could not write {what} '{path}': {reason}. {advice}, then run the command again"


WRITE_ERRORS = (*SPACE_ERRORS, errno.EROFS, errno.EIO)
"""``OSError`` numbers that mean output could not be written, wherever they arise."""


def write_failure(exc: BaseException, where: str | Path) -> WriteError | None:
    """``exc`` (or the ``OSError`` it was raised from) as a :class:`WriteError` when it says
    that output could not be written (:data:`WRITE_ERRORS`), naming its file, else
    ``where`` (the command's output folder); None for anything else."""
    seen: BaseException | None = exc
    while seen is not None and not (isinstance(seen, OSError) and seen.errno in WRITE_ERRORS):
        seen = seen.__cause__ or seen.__context__
    if seen is None:
        return None
    return WriteError(_message("output", Path(seen.filename or where), seen) + ".")


@contextlib.contextmanager
def writing(what: str, path: str | Path, left: str = "") -> Iterator[None]:
    """Turn an ``OSError`` raised inside the block into a :class:`WriteError` saying that
    ``what`` (``"the dataset"``) could not be written at ``path``; ``left`` says what
    is left behind and how to go on."""
    try:
        yield
    except WriteError:
        raise
    except OSError as exc:
        text = _message(what, Path(path), exc)
        raise WriteError(f"{text}{'; ' + left if left else ''}.") from exc


@contextlib.contextmanager
def atomic_write(path: str | Path, what: str, mode: str = "wb",
                 left: str = "") -> Iterator[IO]:
    """A file object to write ``path`` through: the bytes go to a temporary file in the same
    folder, flushed to disk and renamed over ``path`` when the block ends, so ``path`` always
    holds a complete file (the old one when the write fails or the process is killed).
    Failures raise :class:`WriteError` (see :func:`writing`); the temporary file is removed."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}{TEMP_MARK}{os.getpid()}")
    with writing(what, path, left):
        try:
            with open(tmp, mode) as f:
                yield f
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()


def write_text_atomic(path: str | Path, text: str, what: str) -> Path:
    """Write ``text`` into ``path`` atomically (:func:`atomic_write`)."""
    with atomic_write(path, what, "w") as f:
        f.write(text)
    return Path(path)
