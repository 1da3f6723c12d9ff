"""JSON files that people read and write: numeric lists on one line, written atomically; every read
goes through :func:`parse_json`, and the ``expect_*`` checks turn a value of the wrong type or
shape into an InputError that names the file and the field.

A field name (``name``) is written the way a user finds it in the file: ``probe.pitch_mm``,
``layers[0].wires[2].front``, ``line 7: tool_to_base``.
"""

from __future__ import annotations

import json
import math
import re
import sys
import types
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints, is_typeddict

import numpy as np

from probecal.core.errors import InputError
from probecal.core.geometry.transforms import check_transform
from probecal.core.io.files import inside, read_bytes, write_atomic
from probecal.core.io.limits import PARSED_EXPANSION, checked_bytes

_NUMBER_LIST = re.compile(r"\[\s*(-?[\d.eE+-]+(?:,\s*-?[\d.eE+-]+)*)\s*\]")
MAX_INTEGER_DIGITS = 309  # beyond this an integer cannot become a float
T = TypeVar("T")


def _default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def to_json_text(obj: object) -> str:
    """Indented JSON with innermost numeric lists kept on one line."""
    text = json.dumps(obj, indent=2, default=_default, allow_nan=False)
    return _NUMBER_LIST.sub(lambda m: "[" + ", ".join(s.strip() for s in m.group(1).split(",")) + "]", text) + "\n"


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number probecal accepts")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"the number {text[:40]} is out of range")
    return value


def _bounded_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INTEGER_DIGITS:
        raise ValueError(f"a {digits}-digit integer is out of range")
    value = int(text)
    if abs(value) > sys.float_info.max:
        raise ValueError(f"a {digits}-digit integer is out of range")
    return value


def parse_json(text: str | bytes, source: str | Path, problem: str = "not valid JSON") -> Any:
    """The value of JSON text read from ``source``; InputError naming ``source`` and starting with
    ``problem`` when the text is not JSON, nests deeper than Python can follow, or holds NaN,
    Infinity, a float that overflows or an integer too long to become a float."""
    try:
        return json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float, parse_int=_bounded_int)
    except RecursionError:
        raise InputError(source, f"{problem} (nested too deeply)")
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError and the number checks above
        raise InputError(source, f"{problem} ({exc})")


def read_json(path: str | Path) -> dict:
    """A JSON file's top-level object; InputError naming the file when it is missing, not valid
    JSON (see :func:`parse_json`) or not an object."""
    path = Path(path)
    return expect_object(parse_json(read_bytes(path, PARSED_EXPANSION), path), path, "the file")


def json_lines(path: Path, what: str, line_bytes: int, max_line: int) -> Iterator[tuple[int, bytes]]:
    """The complete lines of a JSON-lines file, numbered from 1 (an unterminated last line, a write
    cut short, is left out), once the file's bytes and ``line_bytes`` for every line's value
    would fit the memory limit; InputError naming the file when they would not, or for a line
    longer than ``max_line`` bytes. ``what`` names the lines (plural)."""
    data = read_bytes(path)
    count = data.count(b"\n")
    checked_bytes(path, f"{count} {what}", [len(data) + count * line_bytes])
    start = 0
    for number in range(1, count + 1):
        end = data.index(b"\n", start)
        expect_line_length(path, number, end - start, what, max_line)
        yield number, data[start:end]
        start = end + 1


def expect_line_length(path: Path, number: int, length: int, what: str, max_line: int) -> None:
    """Refuse line ``number`` of a JSON-lines file, ``length`` bytes long, when it is longer than
    any of its ``what`` (plural) may be, ``max_line`` bytes: InputError naming the file."""
    if length > max_line:
        raise InputError(path, f"line {number} is {length} bytes long; {what} take at most {max_line}")


def write_json(path: str | Path, obj: object) -> None:
    """Atomically write ``obj`` as readable JSON."""
    write_atomic(path, to_json_text(obj))


def describe(value: Any) -> str:
    """A short, one-line description of a JSON value for an error message."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value) if abs(value) < 10**15 else "a very large integer"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return f"the string {value!r}" if len(value) <= 40 else f"a string of {len(value)} characters"
    if isinstance(value, list):
        return f"a list of {len(value)} item{'' if len(value) == 1 else 's'}"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def _refuse(value: Any, source: str | Path, name: str, wanted: str) -> InputError:
    return InputError(source, f"{name} must be {wanted}, got {describe(value)}")


def expect_object(value: Any, source: str | Path, name: str) -> dict:
    """``value`` if it is a JSON object."""
    if not isinstance(value, dict):
        raise _refuse(value, source, name, "a JSON object")
    return value


def expect_keys(data: dict, allowed: Collection[str], source: str | Path, name: str) -> dict:
    """``data`` if it has no keys but ``allowed``."""
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise InputError(source, f"{name} has unknown keys {', '.join(map(repr, unknown[:5]))} "
                                 f"(allowed: {', '.join(sorted(allowed))})")
    return data


def expect_list(value: Any, source: str | Path, name: str, length: int | None = None) -> list:
    """``value`` if it is a JSON list (of ``length`` items when given)."""
    if not isinstance(value, list) or (length is not None and len(value) != length):
        raise _refuse(value, source, name, "a list" if length is None else f"a list of {length} items")
    return value


def expect_string(value: Any, source: str | Path, name: str) -> str:
    """``value`` if it is a non-empty string."""
    if not isinstance(value, str) or not value:
        raise _refuse(value, source, name, "a non-empty string")
    return value


def expect_bool(value: Any, source: str | Path, name: str) -> bool:
    """``value`` if it is true or false."""
    if not isinstance(value, bool):
        raise _refuse(value, source, name, "true or false")
    return value


def expect_integer(value: Any, source: str | Path, name: str, minimum: int | None = None) -> int:
    """``value`` if it is a whole number (not a bool, not a float), at least ``minimum``."""
    if not isinstance(value, int) or isinstance(value, bool) or (minimum is not None and value < minimum):
        wanted = "a whole number" if minimum is None else f"a whole number of at least {minimum}"
        raise _refuse(value, source, name, wanted)
    return value


MAX_MAGNITUDE = 1e12
"""The largest number a field of probecal's files may hold (in size): past any length in mm, time
in s or count they hold, and small enough that products and squares of such numbers stay finite."""
MIN_POSITIVE = 1e-9
"""The smallest a positive field may be: its reciprocal stays within MAX_MAGNITUDE."""


def _is_number(value: Any, positive: bool = False) -> bool:
    """A JSON number no larger than MAX_MAGNITUDE (at least MIN_POSITIVE when ``positive``); not
    a bool."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return abs(value) <= MAX_MAGNITUDE and (not positive or value >= MIN_POSITIVE)


def expect_number(value: Any, source: str | Path, name: str, positive: bool = False) -> float:
    """``value`` as a float if it is a finite number (above zero when ``positive``)."""
    if not _is_number(value, positive):
        raise _refuse(value, source, name, f"a positive number (at least {MIN_POSITIVE:g})" if positive
                      else f"a finite number (at most {MAX_MAGNITUDE:g} in size)")
    return float(value)


def expect_numbers(value: Any, source: str | Path, name: str, count: int, positive: bool = False) -> np.ndarray:
    """``value`` as a (count,) float array if it is a list of ``count`` finite numbers (each above
    zero when ``positive``)."""
    if not isinstance(value, list) or len(value) != count or not all(_is_number(v, positive) for v in value):
        kind = (f"positive numbers (from {MIN_POSITIVE:g} to {MAX_MAGNITUDE:g})" if positive
                else f"finite numbers (at most {MAX_MAGNITUDE:g} in size)")
        raise _refuse(value, source, name, f"a list of {count} {kind}")
    return np.array(value, dtype=float)


PIXEL_SPACING_MM = (1e-3, 10.0)
"""The pixel sizes (mm) an ultrasound image may have: a number outside (1e-300, say) is no scanner's
and would overflow or divide by zero downstream."""


def expect_spacing(value: Any, source: str | Path, name: str) -> np.ndarray:
    """``value`` as (sx, sy) mm/px if it is two numbers within :data:`PIXEL_SPACING_MM`."""
    spacing = expect_numbers(value, source, name, count=2)
    low, high = PIXEL_SPACING_MM
    if spacing.min() < low or spacing.max() > high:
        raise _refuse(value, source, name, f"two pixel sizes within [{low:g}, {high:g}] mm")
    return spacing


def expect_matrix(value: Any, source: str | Path, name: str, rigid: bool = False) -> np.ndarray:
    """``value`` as a 4x4 float array if it is 4 rows of 4 finite numbers; when ``rigid``, a
    proper rigid transform (rotation orthonormal with det +1 to ``RIGID_TOLERANCE``, last row
    0 0 0 1)."""
    if not (isinstance(value, list) and len(value) == 4
            and all(isinstance(row, list) and len(row) == 4 and all(_is_number(v) for v in row) for row in value)):
        raise _refuse(value, source, name, f"a 4x4 matrix of finite numbers (4 lists of 4, each at most "
                                           f"{MAX_MAGNITUDE:g} in size)")
    return check_transform(value, name, source, rigid=rigid) if rigid else np.array(value, dtype=float)


def expect_name_inside(value: Any, source: str | Path, name: str, root: Path) -> str:
    """``value`` if it names a file inside the folder ``root`` (see :func:`core.io.files.inside`)."""
    text = expect_string(value, source, name)
    try:
        inside(root, text, source)
    except InputError as exc:
        raise InputError(source, f"{name}: {exc.problem}")
    return text


def expect_typed(value: Any, hint: Any, source: str | Path, name: str) -> Any:
    """``value`` if it is what the type ``hint`` says a file holds there: str, int, float (any
    finite number), bool, None, ``X | Y``, ``Literal[...]``, ``list[X]``, ``dict[str or int,
    X]`` (an int key written as its digits) or a TypedDict (its required keys present, every
    key it names of the right type, others left alone)."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        return _expect_union(value, args, source, name)
    if origin is Literal:
        if value not in args:
            raise _refuse(value, source, name, f"one of {', '.join(map(repr, args))}")
        return value
    if origin is list:
        items = expect_list(value, source, name)
        return [expect_typed(item, args[0], source, f"{name}[{k}]") for k, item in enumerate(items)]
    if origin is dict:
        return _expect_dict(value, args, source, name)
    if is_typeddict(hint):
        return _expect_typeddict(value, hint, source, name)
    return _SCALARS[hint](value, source, name)


def _expect_union(value: Any, args: tuple, source: str | Path, name: str) -> Any:
    if value is None and type(None) in args:
        return None
    first: InputError | None = None
    for arg in (a for a in args if a is not type(None)):
        try:
            return expect_typed(value, arg, source, name)
        except InputError as exc:
            first = first or exc
    assert first is not None
    raise first


def _expect_dict(value: Any, args: tuple, source: str | Path, name: str) -> dict:
    data = expect_object(value, source, name)
    if args[0] is int and not all(re.fullmatch(r"-?\d{1,18}", key) for key in data):
        raise _refuse(value, source, name, "an object whose keys are whole numbers")
    for key, item in data.items():
        expect_typed(item, args[1], source, f"{name}.{key}")
    return data


def _expect_typeddict(value: Any, hint: Any, source: str | Path, name: str) -> dict:
    data = expect_object(value, source, name)
    missing = sorted(hint.__required_keys__ - set(data))
    if missing:
        raise InputError(source, f"{name}.{missing[0]} is missing")
    for key, item_hint in get_type_hints(hint).items():
        if key in data:
            expect_typed(data[key], item_hint, source, f"{name}.{key}")
    return data


def _expect_str(value: Any, source: str | Path, name: str) -> str:
    if not isinstance(value, str):
        raise _refuse(value, source, name, "a string")
    return value


def _expect_none(value: Any, source: str | Path, name: str) -> None:
    if value is not None:
        raise _refuse(value, source, name, "null")


_SCALARS: dict[Any, Callable[[Any, str | Path, str], Any]] = {
    str: _expect_str, int: expect_integer, float: expect_number, bool: expect_bool, type(None): _expect_none,
    Any: lambda value, source, name: value,
}


def optional(data: dict, key: str, check: Callable[..., T], source: str | Path, prefix: str = "",
             **options: Any) -> T | None:
    """``check(data[key], source, prefix + key, **options)``, or None where ``key`` is absent or null."""
    value = data.get(key)
    return None if value is None else check(value, source, prefix + key, **options)


def required(data: dict, key: str, check: Callable[..., T], source: str | Path, prefix: str = "",
             **options: Any) -> T:
    """``check(data[key], source, prefix + key, **options)``; InputError when ``key`` is absent."""
    if key not in data:
        raise InputError(source, f"{prefix}{key} is missing")
    return check(data[key], source, prefix + key, **options)
