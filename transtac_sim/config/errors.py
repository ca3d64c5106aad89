"""The one error type for bad input files, with messages that name the file, the key and the rule."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError


class ConfigError(ValueError):
    """A scene, hardware or material file (or a value in it) that cannot be used.

    ``str(err)`` lists every problem as ``<file>: <key>: <what is wrong>``.
    """

    def __init__(self, source: str | Path, problems: list[tuple[str, str]]):
        self.source = str(source)
        self.problems = problems
        super().__init__("invalid configuration\n  " + "\n  ".join(problem_lines(self.source, problems)))


def problem_lines(source: str | Path, problems: list[tuple[str, str]]) -> list[str]:
    """``<source>: <key>: <what is wrong>`` per problem (``<source>: <what>`` where the key is empty)."""
    return [f"{source}: {key}: {msg}" if key else f"{source}: {msg}" for key, msg in problems]


#: ``kind`` values of the tagged unions in the config models; pydantic puts them in error locations.
_UNION_TAGS = {
    "press", "hold", "slide", "rotate", "roll", "release",
    "elastomer", "dielectric", "diffuse", "fluorescent_pigment",
    "poisson_disk", "grid", "hexagonal", "file",
}

_RANGE_WORDS = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}
#: pydantic's words for a wrong container, in the words of TOML and JSON files.
_TYPE_WORDS = {
    "model_type": "should hold keys and values (a TOML table, a JSON object)",
    "dict_type": "should hold keys and values (a TOML table, a JSON object)",
    "tuple_type": "should be a list", "list_type": "should be a list",
}


def _key_path(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in _UNION_TAGS or str(part).startswith("function-"):
            continue  # discriminated-union tags and validator names are not keys in the file
        else:
            out += ("." if out else "") + str(part)
    return out


def _describe(err: dict) -> str:
    ctx = err.get("ctx") or {}
    given = err.get("input")
    bounds = [f"{_RANGE_WORDS[k]} {v}" for k, v in ctx.items() if k in _RANGE_WORDS]
    if err["type"] == "extra_forbidden":
        return "unknown key (check its spelling and the documented keys)"
    if err["type"] == "missing":  # a list entry (an index) that is not there, or a key
        return "missing: the list is too short" if isinstance(err["loc"][-1], int) else "required key is missing"
    if bounds:
        return f"{given!r} is out of range: allowed {' and '.join(bounds)}"
    msg = _TYPE_WORDS.get(err["type"]) or err["msg"].removeprefix("Value error, ")
    return f"{msg} (got {given!r})" if given is not None and not isinstance(given, dict) else msg


def validation_problems(err: ValidationError) -> list[tuple[str, str]]:
    """``(key, what is wrong)`` for each error of a pydantic ValidationError, in the words of the files."""
    return [(_key_path(e["loc"]), _describe(e)) for e in err.errors()]


def from_validation_error(source: str | Path, err: ValidationError) -> ConfigError:
    """Turn a pydantic ValidationError into a ConfigError naming ``source`` and each key."""
    return ConfigError(source, validation_problems(err))
