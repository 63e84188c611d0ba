"""Atomic file output: write a temporary sibling, then rename it over the target.

A reader (or a resumed run) sees either the old file or the complete new one, never a torn
write; the rename is atomic on POSIX within one directory. A write that fails (a full disk,
no permission) raises :class:`~prdp_fem.errors.OutputError` naming the file it was for, not
the temporary one, and leaves neither behind.

>>> import tempfile, pathlib
>>> target = pathlib.Path(tempfile.mkdtemp()) / "table.csv"
>>> write_text_atomic(target, "a,b\\n")
>>> target.read_text(), sorted(p.name for p in target.parent.iterdir())
('a,b\\n', ['table.csv'])
"""

from __future__ import annotations

import contextlib
import csv
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputError

__all__ = ["atomic_path", "output_error", "write_csv_atomic", "write_text_atomic"]


def output_error(path: str | os.PathLike, error: OSError) -> OutputError:
    """``error`` (raised writing ``path``) as an :class:`OutputError` naming ``path``."""
    return OutputError(path, f"could not be written ({error.strerror or error}); expected a "
                       "writable path on a disk with free space")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` (same suffix, so writers that go by the suffix
    still work); it replaces ``path`` when the block ends, and is removed if the block fails."""
    path = Path(path)
    # unique per writer: two processes writing the same target never share a temporary file
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as error:  # ENOSPC, EACCES, EROFS...: name the file the user asked for
        raise output_error(path, error) from error
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """``Path(path).write_text(text)``, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_csv_atomic(path: str | os.PathLike, rows: list[dict]) -> None:
    """``rows`` as CSV, the first row's keys as the header (``None`` as an empty cell),
    atomically; an empty ``rows`` writes an empty file.

    >>> import tempfile, pathlib
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "rows.csv"
    >>> write_csv_atomic(target, [{"run": "prdp", "step": None}, {"run": "fixed", "step": 3}])
    >>> target.read_text().splitlines()
    ['run,step', 'prdp,', 'fixed,3']
    """
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as stream:
        if rows:
            writer = csv.DictWriter(stream, fieldnames=list(rows[0]))
            writer.writeheader()
            for row in rows:
                writer.writerow({k: ("" if v is None else v) for k, v in row.items()})
