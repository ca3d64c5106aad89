"""Errors of the perception package: one line that names the file and says what to do."""

from __future__ import annotations

from pathlib import Path


def output_file(path: Path | str) -> Path:
    """``path`` as a file to write; PerceptionInputError where it is a folder."""
    path = Path(path)
    if path.is_dir():
        raise PerceptionInputError(path, "is a folder", "give the file to write, e.g. --out results.json")
    return path


class PerceptionInputError(Exception):
    """Bad input (a missing or unreadable image, a wrong colour format, a model file that is not one).

    ``str(e)`` is ``"<path>: <what is wrong>; <what to do>"``.
    """

    def __init__(self, path: Path | str, problem: str, fix: str = "") -> None:
        self.path, self.problem, self.fix = str(path), problem, fix
        super().__init__(f"{self.path}: {problem}" + (f"; {fix}" if fix else ""))
