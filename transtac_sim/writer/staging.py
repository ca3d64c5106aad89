"""A command's output folder replaced only when the command ends: a run into a folder that already holds files
writes into a hidden folder beside it (``.<name>.*.partial``), whose files then replace the earlier run's. An
interrupted or crashed run leaves the earlier one as it was (``simulate``, ``reconstruct``)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def staged_output(out: Path, clear_previous: Callable[[Path], None], last: tuple[str, ...] = ()) -> Iterator[Path]:
    """The folder to write a run into: ``out`` itself where it is new or empty, else a hidden folder beside it.
    When the block ends without an exception, ``clear_previous(out)`` removes the earlier run's files and the staged
    files are moved into ``out`` (each atomically; the names in ``last``, e.g. a summary, after the others). On an
    exception the staged folder is removed and ``out`` is left as it was."""
    out = Path(out)
    if not (out.is_dir() and any(out.iterdir())):
        out.mkdir(parents=True, exist_ok=True)
        yield out
        return
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        yield work
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    clear_previous(out)
    files = sorted((p for p in work.rglob("*") if p.is_file()), key=lambda p: (p.name in last, str(p)))
    for p in files:
        target = out / p.relative_to(work)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(p, target)
    shutil.rmtree(work)
