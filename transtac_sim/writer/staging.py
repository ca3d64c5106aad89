"""A command's output folder replaced only when the command ends (``simulate``, ``reconstruct``).

A run into a folder that already holds files writes into a hidden folder inside it (``.partial-*``: the same
filesystem, so the files move in by rename, and no need to write beside ``out``). When the run ends its files
replace the earlier run's: the new files move in first (each rename atomic), then the earlier run's files that no
new file replaced are removed, then the files named ``last`` (a summary) move in. An interrupted or crashed run
leaves the earlier one as it was; a hidden folder left by a killed process is removed by the next run.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

STAGE_PREFIX = ".partial-"


def own_entries(out: Path) -> list[Path]:
    """The entries of ``out`` other than staging folders."""
    return [p for p in Path(out).iterdir() if not p.name.startswith(STAGE_PREFIX)]


@contextmanager
def staged_output(out: Path, earlier_files: Callable[[Path], list[Path]], last: tuple[str, ...] = ()) -> Iterator[Path]:
    """The folder to write a run into: ``out`` itself where it is new or empty, else a hidden folder inside it
    (module docstring). ``earlier_files(out)`` lists the earlier run's files, those a finished run replaces; the names
    in ``last`` move in after the others. On an exception the hidden folder is removed and ``out`` is left as it
    was."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for p in out.glob(f"{STAGE_PREFIX}*"):  # left by a run that was killed
        shutil.rmtree(p, ignore_errors=True)
    if not own_entries(out):
        yield out
        return
    work = Path(tempfile.mkdtemp(prefix=STAGE_PREFIX, dir=out))
    try:
        yield work
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    new = sorted((p for p in work.rglob("*") if p.is_file()), key=lambda p: (p.name in last, str(p)))
    names = {p.relative_to(work) for p in new}
    stale = [p for p in earlier_files(out) if p.relative_to(out) not in names]
    for p in new:
        if p.name in last:
            for q in stale:
                q.unlink(missing_ok=True)
            stale = []
        target = out / p.relative_to(work)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(p, target)
    for q in stale:
        q.unlink(missing_ok=True)
    shutil.rmtree(work)
