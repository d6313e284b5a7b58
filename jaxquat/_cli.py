"""The command line: `python -m jaxquat {demo,simulate,fit,bench}` (also the `jaxquat` console script).

- `demo`: a 10⁵-body rigid-body ensemble (uncertainty propagation through the tennis-racket
  instability), a fit of ω to noisy attitude observations, a summary table and a PNG figure.
- `simulate`: an ensemble from options or a TOML file; writes an ensemble directory and a summary.
- `fit`: fits ω to a CSV of `t,w,x,y,z` (header optional); `--json` for machine-readable output.
  q0 is the orientation at t0, the first observation's time (printed with it).
- `bench`: the benchmark suite with its quick preset.

Every bad argument or file gives exactly one line on stderr (naming the file and line where it
applies) and exit status 2; an unexpected failure gives one line and exit status 1. Never a traceback.
"""

from __future__ import annotations

import _thread
import argparse
import contextlib
import importlib
import json
import math
import os
import re
import signal
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

_PROG = "jaxquat"
_DTYPES = ("float32", "float64")


class CommandLineError(Exception):
    """A problem with the user's arguments or files: reported in one line, exit status 2."""

    def __init__(self, message: str, prog: str = _PROG):
        super().__init__(message)
        self.prog = prog


class _Interrupted(KeyboardInterrupt):
    """Ctrl-C during a command, with what the command left behind (said after "interrupted")."""


# An interrupt that `_redelivering` caught in a callback and has not been raised yet.
_PENDING_INTERRUPT = [False]


def _redelivering(previous: Callable[[Any], None]) -> Callable[[Any], None]:
    """A `sys.unraisablehook` that gives interrupts back to the program instead of printing them.

    A Ctrl-C that lands while Python runs a callback it cannot raise from (JAX's garbage-collection
    callback, a `__del__`) is only reported ("Exception ignored in: …", a traceback), and the command
    then ran to its end and exited 0 (a probe hit it about once in 10–45 tries). The signal is
    tripped again instead, and its KeyboardInterrupt is raised where the command can see it.
    """

    def hook(unraisable) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            _PENDING_INTERRUPT[0] = True  # (`main` raises it if the command returns first)

            def later() -> None:
                # Tripped from another thread once this hook has returned: tripped here, the
                # handler would run at once, inside the hook, whose exceptions are lost as well.
                time.sleep(0.01)
                _thread.interrupt_main(signal.SIGINT)

            # A bare thread: `threading`'s locks are best not taken inside a GC callback, and at
            # interpreter shutdown no thread can start (nothing is left to interrupt then).
            with contextlib.suppress(RuntimeError):
                _thread.start_new_thread(later, ())
            return
        previous(unraisable)

    return hook


class _Parser(argparse.ArgumentParser):
    """An `ArgumentParser` whose errors become one-line `CommandLineError`s instead of usage + exit,
    and whose options that take a value may be given only once (`_Once`, the default action)."""

    def error(self, message: str):  # noqa: D102 (argparse's signature)
        raise CommandLineError(message, prog=self.prog)

    def _print_message(self, message: str, file=None) -> None:
        # argparse ignores an OSError here: `jaxquat --help > /dev/full` printed nothing and exited
        # 0. Written and flushed, a failure reaches `main` (one line, status 2).
        if message:
            file = file or sys.stderr
            file.write(message)
            file.flush()

    def add_argument(self, *names, **kwargs):  # noqa: D102 (argparse's signature)
        if names and names[0].startswith("-") and "action" not in kwargs:
            kwargs["action"] = _Once
        return super().add_argument(*names, **kwargs)


class _Once(argparse.Action):
    """Store an option that may be given only once (argparse's default keeps the last silently:
    `--bodies 10 … --bodies 12` ran 12 bodies without a word)."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = namespace.__dict__.setdefault("_given", set())
        if self.dest in given:
            previous = getattr(namespace, self.dest)
            raise argparse.ArgumentError(
                self,
                f"may be given only once, got {_plain(previous)!r} and then {_plain(values)!r}",
            )
        given.add(self.dest)
        setattr(namespace, self.dest, values)


def _plain(value):
    """A path as its text (the message showed `PosixPath('/a')`); anything else as it is."""
    return str(value) if isinstance(value, os.PathLike) else value


# ----------------------------------------------------------------------------------------------------
# Value parsers (used for options and for TOML values)


_INTEGER = re.compile(r"[+-]?[0-9]+")


def _integer(text) -> int:
    """`int(text)` for plain decimal integers only (not `1_0`, `1.0`, non-ASCII digits)."""
    if isinstance(text, bool) or not (
        isinstance(text, int) or (isinstance(text, str) and _INTEGER.fullmatch(text))
    ):
        raise ValueError(text)
    return int(text)


def _positive_int(text: str) -> int:
    try:
        value = _integer(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


_STEPS_MAX = 2**31 - 1  # the ensemble's step counter is an int32


def _step_count(text: str) -> int:
    """A number of steps: a positive integer that fits the ensemble's int32 step counter."""
    value = _positive_int(text)
    if value > _STEPS_MAX:
        raise argparse.ArgumentTypeError(f"must be at most 2**31 - 1 = {_STEPS_MAX}, got {value}")
    return value


# The CLI draws the whole ensemble on one device, at 100 bytes a body in float32 (q0 and ω, 28, and
# the random bits they are drawn from, 72), so 2**40 bodies already need 110 TB: more than any machine
# holds. Counts up to the bound fail cleanly with "out of memory" (exit 2) where they do not fit
# (`check_simulate_memory`, before the kernel's OOM killer would end the process silently); far
# beyond it XLA aborts the process on the array's size (from 2**58) and past 2**63 - 1 the shape does
# not fit XLA's int64, neither of which can be reported in one line.
_BODIES_MAX = 2**40


def _body_count(text: str) -> int:
    """A number of bodies: a positive integer no larger than any machine could draw (`_BODIES_MAX`)."""
    value = _positive_int(text)
    if value > _BODIES_MAX:
        raise argparse.ArgumentTypeError(f"must be at most 2**40 = {_BODIES_MAX}, got {value}")
    return value


_SEED_MAX = 2**32 - 1


def _seed(text: str) -> int:
    """A random seed: an integer in 0 … 2³² − 1 (JAX keeps 32 bits of it without x64)."""
    try:
        value = _integer(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= value <= _SEED_MAX:
        raise argparse.ArgumentTypeError(
            f"must be an integer from 0 to {_SEED_MAX} (2**32 - 1), got {value}"
        )
    return value


def _exact(value: float) -> str:
    """`value` as `:g` writes it when that is exact, else its shortest repr: `1.7e+09` named two
    different Unix times (1700000000.1 and 1700000000.2) alike."""
    short = f"{value:g}"
    return short if float(short) == value else repr(float(value))


def _positive_float(text: str) -> float:
    value = _finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {_exact(value)}")
    return value


def _nonnegative_float(text: str) -> float:
    value = _finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {_exact(value)}")
    return value


class _TomlFloat(float):
    """A TOML float that keeps its text, so `dt = 1e-400` is reported as underflowing, not as 0."""

    text: str

    def __new__(cls, text: str) -> _TomlFloat:
        value = super().__new__(cls, text)
        value.text = text
        return value


def _finite_float(text: str) -> float:
    if isinstance(text, _TomlFloat):
        text = text.text.replace("_", "")  # TOML allows 1_000.5
    if isinstance(text, bool) or not (
        isinstance(text, (int, float)) or (isinstance(text, str) and _is_number(text))
    ):
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}")
    try:
        value = float(text)
    except (TypeError, ValueError, OverflowError):
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    if value == 0 and isinstance(text, str) and re.search(r"[1-9]", re.split("[eE]", text)[0]):
        # `1e-400`: a non-zero number below the smallest float64 would otherwise be "got 0".
        raise argparse.ArgumentTypeError(
            f"{text!r} underflows to 0 (below {math.ulp(0.0):g}, the smallest float64)"
        )
    return value


def _vector3(text: str) -> list[float]:
    parts = text.split(",") if isinstance(text, str) else text
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"must be three comma-separated numbers, got {text!r}")
    # `--omega-mean "0, 0, 1"`: spaces after the commas are fine.
    return [_finite_float(p.strip() if isinstance(p, str) else p) for p in parts]


def _inertia(text: str) -> list[float]:
    moments = _vector3(text)
    if any(m <= 0 for m in moments):
        raise argparse.ArgumentTypeError(f"principal moments must be positive, got {text!r}")
    return moments


# ----------------------------------------------------------------------------------------------------
# Reading files


def _read_text(path: str, what: str) -> str:
    if not os.path.exists(path):
        raise CommandLineError(f"{path}: no such file ({what})")
    if os.path.isdir(path):
        raise CommandLineError(f"{path}: is a directory, expected a {what}")
    try:
        with open(path, encoding="utf-8-sig") as f:  # a leading byte-order mark (Excel) is dropped
            text = f.read(_MAX_TEXT + 1)
    except UnicodeDecodeError:
        raise CommandLineError(f"{path}: not a UTF-8 text file ({what})") from None
    except OSError as e:
        raise CommandLineError(f"{path}: cannot read ({e.strerror})") from None
    if len(text) > _MAX_TEXT:  # (/dev/zero, a wrong file: read to the end, it ran out of memory)
        raise CommandLineError(f"{path}: longer than {_MAX_TEXT:,} characters, expected a {what}")
    return text


# The longest text file read (1 Gi characters: a CSV of some 15 million observations).
_MAX_TEXT = 2**30

_LINE_END = re.compile(r"\r\n|\r|\n")


def _lines(text: str) -> list[str]:
    """The lines of `text`, numbered as editors, `wc -l` and `sed -n Np` number them.

    Only LF, CR LF and CR end a line (the line ends of a CSV or TOML file): `str.splitlines` also
    splits at form feed, 0x1C-0x1E, NEL (U+0085), U+2028 and U+2029, which may stand in a comment.
    """
    return _LINE_END.split(text)


_CSV_COLUMNS = ("t", "w", "x", "y", "z")


def _unquote(field: str) -> str:
    """A CSV field without its double quotes (R's write.csv quotes the header: `"t","w",…`)."""
    if len(field) >= 2 and field[0] == field[-1] == '"':
        return field[1:-1].strip().replace('""', '"')
    return field


def read_observations_csv(path: str):
    """Read `t,w,x,y,z` rows (header optional; blank lines and `#` comments skipped).

    Returns `(origin, times (T,), quaternions (T, 4), first)`, the arrays float64 NumPy. `first` is
    the first time as the file writes it, and `origin` the same (None when that is 0); `times` count
    from `origin`: each is the
    double nearest the exact (decimal) difference, so times far from zero keep their digits (at a
    Unix time in seconds float64's own spacing is 2.4e-7 s; at 1e15 it is 0.125 s). Raises
    `CommandLineError` naming the file and line of the first problem.
    """
    import decimal

    import numpy as np

    text = _read_text(path, "CSV of t,w,x,y,z")
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    time_fields: list[str] = []
    seen_content = False
    for number, raw in enumerate(_lines(text), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = [_unquote(f.strip()) for f in line.split(",")]
        if len(fields) == 1 and (";" in line or len(line.split()) > 1):
            # Another separator (a spreadsheet export, or columns separated by spaces or tabs):
            # neither a wrong header nor one column.
            separator = ";" if ";" in line else "\t" if "\t" in line else " "
            raise CommandLineError(
                f"{path} line {number}: columns must be separated by commas, got {separator!r}"
            )
        if not seen_content:
            seen_content = True
            names = tuple(f.lower() for f in fields)
            if names == _CSV_COLUMNS:
                continue
            # A line with no number in it is a (wrong) header; one with numbers is a data row (with a
            # typo, reported below as such).
            if not any(_is_number(f) for f in fields):
                raise CommandLineError(
                    f"{path} line {number}: header must be t,w,x,y,z, got {line!r}"
                )
        if len(fields) != 5:
            raise CommandLineError(
                f"{path} line {number}: expected 5 columns (t,w,x,y,z), got {len(fields)}"
            )
        values = []
        for name, field in zip(_CSV_COLUMNS, fields, strict=True):
            if not _is_number(field):
                raise CommandLineError(
                    f"{path} line {number}: column {name} is not a number: {field!r}"
                )
            value = float(field)
            if not math.isfinite(value):
                raise CommandLineError(
                    f"{path} line {number}: column {name} is not finite ({field})"
                )
            values.append(value)
        if rows and values[0] <= rows[-1][0] and not _rounded_alike(fields[0], time_fields[-1]):
            later, earlier = _exact(values[0]), _exact(rows[-1][0])
            if later == earlier:  # (one double: say what the file wrote)
                later, earlier = fields[0], time_fields[-1]
            raise CommandLineError(
                f"{path} line {number}: times must increase, but t = {later} follows t = {earlier}"
            )
        if values[1] == values[2] == values[3] == values[4] == 0.0:
            raise CommandLineError(f"{path} line {number}: the quaternion (w,x,y,z) is zero")
        largest = max(abs(v) for v in values[1:])
        if largest < sys.float_info.min:
            raise CommandLineError(
                f"{path} line {number}: the quaternion (w,x,y,z) is too small to normalise "
                f"accurately (largest component {largest:g} is below {sys.float_info.min:g})"
            )
        rows.append(values)
        time_fields.append(fields[0])
        line_numbers.append(number)
    if not rows:
        what = "empty file" if not text.strip() else "only a header, blank lines or comments"
        raise CommandLineError(f"{path}: no data rows ({what})")
    if len(rows) < 3:
        raise CommandLineError(f"{path}: need at least 3 observations to fit ω, got {len(rows)}")
    data = np.asarray(rows, dtype=np.float64)
    origin = time_fields[0] if rows[0][0] != 0 else None
    if origin is not None or not _times_hold(data[:, 0].tolist()):
        offsets = _offsets(path, time_fields, decimal.Decimal(origin or 0), line_numbers)
        if offsets is None:  # (a span beyond float64: the fit refuses it, naming the span)
            return None, data[:, 0], data[:, 1:], time_fields[0]
        data[:, 0] = offsets
    return origin, data[:, 0], data[:, 1:], time_fields[0]


def _rounded_alike(later: str, earlier: str) -> bool:
    """Whether the time `later` exceeds `earlier` though both read as the same double."""
    return float(later) == float(earlier) and _decimal(later) > _decimal(earlier)


def _decimal(text: str):
    """The number `text` as an exact `decimal.Decimal`; one with an exponent beyond Decimal's range
    (±10¹⁸) as the double it reads as (0: an infinite one was refused already)."""
    import decimal

    try:
        return decimal.Decimal(text)
    except decimal.InvalidOperation:
        return decimal.Decimal(float(text))


def _wide_context(digits: int):
    """A `decimal.Context` of `digits` significant digits and no bound on the exponent."""
    import decimal

    return decimal.Context(prec=digits, Emin=decimal.MIN_EMIN, Emax=decimal.MAX_EMAX)


def _times_hold(times: list[float]) -> bool:
    """Whether rounding to the nearest double moved no time by more than a thousandth of the
    shortest interval (a bound on half a unit in the last place at the largest |t|)."""
    shortest = min(b - a for a, b in zip(times, times[1:], strict=False))
    return math.ulp(max(abs(times[0]), abs(times[-1]))) <= 2e-3 * shortest  # (ulp(0) / 2 is 0)


def _offsets(path: str, texts: list[str], origin, lines: list[int]) -> list[float] | None:
    """The times `texts` counted from `origin` (a `decimal.Decimal`), each the double nearest the
    exact offset (0.6 s per 10⁶ rows), or None if the last overflows. Raises `CommandLineError`
    when rounding moved one by more than a thousandth of the shortest interval (a span ~10¹³ times
    the shortest interval): the fit would be quietly off (0.3 s steps read as multiples of 0.125
    fitted ω 0.3 % off)."""
    import decimal

    # 60 digits: the offsets are rounded once more, to 17; two times that differ only beyond the
    # 60th digit of their offsets (no double tells them apart) are refused below.
    context = _wide_context(60)
    exact = [context.subtract(_decimal(text), origin) for text in texts]
    offsets = [float(e) for e in exact]
    if not math.isfinite(offsets[-1]):
        return None
    if _times_hold(offsets):
        return offsets
    intervals = [context.subtract(b, a) for a, b in zip(exact, exact[1:], strict=False)]
    shortest = min(intervals)
    if shortest <= 0:
        k = intervals.index(shortest) + 1
        raise CommandLineError(
            f"{path} line {lines[k]}: float64 cannot tell the time {texts[k]} from the one "
            f"before it, {texts[k - 1]} (counted from the first observation)"
        )
    for text, offset, value, number in zip(texts, exact, offsets, lines, strict=True):
        moved = context.copy_abs(context.subtract(offset, decimal.Decimal(value)))
        if moved > context.divide(shortest, 1000):
            raise CommandLineError(
                f"{path} line {number}: float64 holds the time {text} only to {moved:.3g} s "
                f"(counted from the first observation), too coarse for intervals of {shortest:.6g}"
            )
    return offsets


# A decimal number as people write it (and `nan`/`inf`, rejected later as not finite). Not Python's
# `float()` syntax, which also takes `1_0`, non-ASCII digits and surrounding whitespace.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def _is_number(text: str) -> bool:
    return bool(_NUMBER.fullmatch(text) or _NON_FINITE.fullmatch(text))


# Options of `simulate` that a TOML file may set: name → parser (`bool` / `str`: the TOML type).
_SIMULATE_KEYS: dict[str, Any] = {
    "bodies": _body_count,
    "steps": _step_count,
    "dt": _positive_float,
    "method": str,
    "frame": str,
    "omega_scale": _nonnegative_float,
    "omega_mean": _vector3,
    "inertia": _inertia,
    "seed": _seed,
    "dtype": str,
    "save_every": _positive_int,
    "chunk_size": _positive_int,
    "output": str,
    "statistics": bool,
}
_INTEGER_KEYS = ("bodies", "steps", "seed", "save_every", "chunk_size")
_VECTOR_KEYS = ("omega_mean", "inertia")
_FRAMES = ("world", "body")


def _methods(rigid: bool) -> tuple[str, ...]:
    from ._integrate import METHODS

    return tuple(m for m in METHODS if not (rigid and m.startswith("magnus")))


def _is_real(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def read_simulate_toml(path: str) -> dict[str, Any]:
    """Read and check a `simulate` configuration; errors name the file, the line and the key."""
    return _read_simulate_toml(path)[0]


def _read_simulate_toml(path: str) -> tuple[dict[str, Any], dict[str, str]]:
    """`read_simulate_toml`, and for each key where it was set (`"file line N"`, for messages)."""
    import tomllib

    text = _read_text(path, "TOML configuration")
    try:
        table = tomllib.loads(text, parse_float=_TomlFloat)
    except tomllib.TOMLDecodeError as e:
        raise CommandLineError(f"{path}: invalid TOML: {e}") from None
    if isinstance(table.get("simulate"), dict):
        # Options in a [simulate] table: nothing else may stand beside it.
        for key, value in table.items():
            if key != "simulate":
                raise CommandLineError(
                    f"{_table_where(text, path, key)}: unknown table [{key}] beside [simulate]"
                    if isinstance(value, dict)
                    else f"{_table_where(text, path, key)}: key {key!r} outside [simulate] "
                    "(set every option in the [simulate] table, or none)"
                )
        table = table["simulate"]

    def where(key: str) -> str:
        """The file and the line setting `key` when exactly one line plainly does (`key = …`, the key
        quoted or under `simulate.`); the file alone when none or several do — a key's text may also
        stand in a multi-line string, and an escaped, inline-table or other key form is not read
        here — so a line that is named is never the wrong one. A file with a multi-line string or an
        escape in a key is named alone: a `bodies = 10` line inside a string, with the key set as
        "bod\\u0069es" on another line, was named as the line setting it."""
        if any("\\" in line.split("=", 1)[0] for line in _lines(text)):
            return path
        names = {key, f"simulate.{key}"}
        return _line_where(
            text,
            path,
            lambda line: "=" in line and line.split("=", 1)[0].strip().strip("\"'") in names,
        )

    config: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for key, value in table.items():
        if key not in _SIMULATE_KEYS:
            known = ", ".join(sorted(_SIMULATE_KEYS))
            if isinstance(value, dict):  # `[simulat]`: a misspelt table
                raise CommandLineError(
                    f"{_table_where(text, path, key)}: unknown table [{key}] (expected [simulate] "
                    f"or top-level keys: {known})"
                )
            raise CommandLineError(f"{where(key)}: unknown key {key!r} (known: {known})")
        parse = _SIMULATE_KEYS[key]
        if parse is bool:
            if not isinstance(value, bool):
                raise CommandLineError(f"{where(key)}: {key} must be true or false, got {value!r}")
        elif parse is str:
            if not isinstance(value, str):
                raise CommandLineError(f"{where(key)}: {key} must be a string, got {value!r}")
            choices = {"frame": _FRAMES, "dtype": _DTYPES, "method": _methods(rigid=False)}.get(key)
            if choices is not None and value not in choices:
                raise CommandLineError(
                    f"{where(key)}: {key} must be one of {', '.join(choices)}, got {value!r}"
                )
            if key == "output" and not value:
                raise CommandLineError(f"{where(key)}: output must name a directory, got ''")
        else:
            # Numbers must be TOML numbers (a quoted "0.1" is a string, not a number).
            if key in _INTEGER_KEYS:
                if isinstance(value, bool) or not isinstance(value, int):
                    raise CommandLineError(
                        f"{where(key)}: {key} must be an integer (unquoted), got {value!r}"
                    )
            elif key in _VECTOR_KEYS:
                if not isinstance(value, list) or not all(_is_real(v) for v in value):
                    raise CommandLineError(
                        f"{where(key)}: {key} must be an array of three numbers (unquoted), "
                        f"got {value!r}"
                    )
            elif not _is_real(value):
                raise CommandLineError(
                    f"{where(key)}: {key} must be a number (unquoted), got {value!r}"
                )
            try:
                value = parse(
                    value if key in _VECTOR_KEYS or isinstance(value, _TomlFloat) else str(value)
                )
            except argparse.ArgumentTypeError as e:
                raise CommandLineError(f"{where(key)}: {key} {e}") from None
        config[key] = value
        sources[key] = where(key)
    return config, sources


def _table_where(text: str, path: str, name: str) -> str:
    """The file and the line opening the table or key `name` (`[name]`, `[name.x]`, `[[name]]`,
    `name = {…}`, `name.x = …`, the name quoted or not) when exactly one line plainly does; else the
    file alone (as `where` in `_read_simulate_toml`: never a wrong line)."""
    quoted = rf"""(?:{re.escape(name)}|"{re.escape(name)}"|'{re.escape(name)}')"""
    opening = re.compile(rf"\s*(?:\[\[?\s*{quoted}\s*[\].]|{quoted}\s*[.=])")
    return _line_where(text, path, opening.match)


def _line_where(text: str, path: str, matches: Callable[[str], Any]) -> str:
    """`"path line N"` when exactly one line of `text` `matches`, else `path` alone; also alone when
    the text holds a multi-line string, whose lines could look like settings."""
    if '"""' in text or "'''" in text:
        return path
    numbers = [number for number, line in enumerate(_lines(text), start=1) if matches(line)]
    return f"{path} line {numbers[0]}" if len(numbers) == 1 else path


# ----------------------------------------------------------------------------------------------------
# Shared set-up


def _setup_jax(dtype: str) -> None:
    import jax

    if dtype == "float64":
        jax.config.update("jax_enable_x64", True)


def _random_ensemble(seed: int, bodies: int, omega_mean, omega_scale: float, dtype):
    """Haar-random orientations and ω = mean + scale·N(0, I), made with `jax.random`.

    The draws are made in float32 whatever `dtype` (then renormalised in `dtype`): `jax.random`
    draws other numbers in each dtype, so the same seed gave float32 and float64 runs different
    bodies (median turn 94° against 106° at seed 0), and the two could not be compared.
    """
    import jax
    import jax.numpy as jnp

    from ._algebra import normalize
    from ._geometry import random

    key_q, key_w = jax.random.split(jax.random.key(seed))
    q0 = normalize(random(key_q, (bodies,), jnp.float32).astype(dtype))
    noise = jax.random.normal(key_w, (bodies, 3), jnp.float32).astype(dtype)
    omega = jnp.asarray(omega_mean, dtype)[None, :] + jnp.asarray(omega_scale, dtype) * noise
    return q0, omega


def _throughput(rate: float) -> str:
    """Body-steps per second with three significant figures at any size (a 10-body run is not
    "0.0 M")."""
    for scale, prefix in ((1e9, "G "), (1e6, "M "), (1e3, "k ")):
        if rate >= scale:
            return f"{rate / scale:.3g} {prefix}body-steps/s"
    return f"{rate:.3g} body-steps/s"


def _percentiles(values, qs=(5, 50, 95)):
    import numpy as np

    return [float(v) for v in np.percentile(np.asarray(values, dtype=np.float64), qs)]


# ----------------------------------------------------------------------------------------------------
# simulate


def _cmd_simulate(args: argparse.Namespace) -> int:
    config: dict[str, Any] = {
        "bodies": 10_000,
        "steps": 1_000,
        "dt": 1e-2,
        "method": None,
        "frame": None,
        "omega_scale": 1.0,
        "omega_mean": [0.0, 0.0, 0.0],
        "inertia": None,
        "seed": 0,
        "dtype": "float32",
        "save_every": None,
        "chunk_size": None,
        "output": "jaxquat_ensemble",
        "statistics": True,
    }
    # Where each value came from, for error messages: the option, or the file and line.
    sources = {key: f"--{key.replace('_', '-')}" for key in config}
    if args.config is not None:
        from_file, file_sources = _read_simulate_toml(args.config)
        config.update(from_file)
        sources.update(file_sources)
    for key in config:  # command-line options override the file
        value = getattr(args, key, None)
        if value is not None:
            config[key] = value
            sources[key] = f"--{key.replace('_', '-')}"
    if config["dtype"] not in _DTYPES:
        raise CommandLineError(
            f"{sources['dtype']}: dtype must be float32 or float64, got {config['dtype']!r}"
        )
    rigid = config["inertia"] is not None
    if config["method"] is not None and config["method"] not in _methods(rigid):
        kind = "rigid bodies (inertia given)" if rigid else "kinematic bodies"
        raise CommandLineError(
            f"{sources['method']}: method for {kind} must be one of "
            f"{', '.join(_methods(rigid))}, got {config['method']!r}"
        )
    if config["frame"] is not None and config["frame"] not in _FRAMES:
        raise CommandLineError(
            f"{sources['frame']}: frame must be world or body, got {config['frame']!r}"
        )
    if not config["output"]:
        raise CommandLineError(f"{sources['output']}: must name a directory, got ''")
    if os.path.exists(config["output"]) and not os.path.isdir(config["output"]):
        raise CommandLineError(
            f"{sources['output']}: {config['output']} exists and is not a directory"
        )
    _check_representable(config, sources, config["dtype"])
    _setup_jax(config["dtype"])

    import jax
    import jax.numpy as jnp
    import numpy as np

    from ._ensemble import simulate_ensemble

    check_simulate_memory(config["bodies"], _memory_available())

    dtype = jnp.dtype(config["dtype"])
    q0, omega = _random_ensemble(
        config["seed"], config["bodies"], config["omega_mean"], config["omega_scale"], dtype
    )
    if not bool(jnp.all(jnp.isfinite(omega))):
        raise CommandLineError(
            f"the initial angular velocities ω = omega_mean + omega_scale·N(0, I) overflow "
            f"{dtype.name} ({sources['omega_mean']} {config['omega_mean']}, "
            f"{sources['omega_scale']} {_exact(config['omega_scale'])}); use smaller values"
            f"{_or_float64(dtype.name)}"
        )
    inertia = None if config["inertia"] is None else jnp.asarray(config["inertia"], dtype)
    index_before = _file_identity(os.path.join(config["output"], "index.json"))
    method = config["method"] or ("cf4" if inertia is not None else "euler")
    frame = config["frame"] or ("body" if inertia is not None else "world")
    # Everything that determines the result, for index.json (`load_ensemble(...)["metadata"]["run"]`):
    # the run is the same again from these options (with the same jax and jaxquat versions).
    run = {
        "command": "jaxquat simulate",
        "jaxquat_version": _version(),
        "jax_version": jax.__version__,
        **{key: config[key] for key in _RUN_KEYS},
        "method": method,
        "frame": frame,
    }
    try:
        result = simulate_ensemble(
            q0,
            omega,
            config["dt"],
            config["steps"],
            inertia=inertia,
            frame=frame,
            method=method,
            save_every=config["save_every"],
            statistics=config["statistics"],
            chunk_size=config["chunk_size"],
            path=config["output"],
            metadata=run,
            progress=_show_progress(args.no_progress),
        )
    except KeyboardInterrupt:
        raise _Interrupted(_saved_before_interrupt(config["output"], index_before)) from None
    outputs = {"final orientations": result.final, "final angular velocities": result.final_omega}
    if result.total_angle is not None:
        outputs["total rotation angles"] = result.total_angle
    _check_finite_results(
        outputs,
        f"the simulation (dt {_exact(config['dt'])}, omega_scale {_exact(config['omega_scale'])}, "
        f"{dtype.name}); {_directory(config['output'])} holds the invalid results. Use a smaller "
        f"--dt / --omega-scale{_or_float64(dtype.name)}",
    )
    kind = "rigid" if inertia is not None else "kinematic"
    rows = [
        (
            "ensemble",
            f"{_count(config['bodies'], f'{kind} body', f'{kind} bodies')}, "
            f"{_count(config['steps'], 'step')} of {_exact(config['dt'])} s",
        ),
        (
            "method / frame / dtype",
            f"{method} / {frame} / {dtype.name}",
        ),
        ("devices", f"{len(jax.devices())} ({jax.devices()[0].platform})"),
        (
            "wall time",
            f"{result.seconds:.2f} s in {_count(result.num_chunks, 'chunk')}, compile included",
        ),
        ("throughput", _throughput(result.throughput)),
    ]
    p5, p50, p95 = _percentiles(np.degrees(np.asarray(result.angle_from_start)))
    rows.append(("angle from start (5/50/95 %)", f"{p5:.2f}° / {p50:.2f}° / {p95:.2f}°"))
    if result.total_angle is not None:
        total = np.asarray(result.total_angle, dtype=np.float64)
        rows.append(("total rotation (mean / max)", f"{total.mean():.3f} / {total.max():.3f} rad"))
    saved = "final state"
    if config["save_every"]:
        every, steps = config["save_every"], config["steps"]
        # The saved steps are 0, k, 2k, …; the last step is among them only when k divides the steps.
        period = "every step" if every == 1 else f"every {every:,} steps"
        last = steps // every * every
        saved = f"{_count(steps // every + 1, 'state')} ({period}, steps 0 to {last}) and the final state"
    rows.append(
        ("written", f"{_directory(config['output'])} ({saved}; read with jaxquat.load_ensemble)")
    )
    if index_before is not None:  # the writer removed the previous run's files first
        rows.append(("replaced", f"the ensemble that was in {_directory(config['output'])}"))
    _print_table(rows)
    return 0


# The options recorded in index.json (with the method and frame the run used).
_RUN_KEYS = (
    "bodies",
    "steps",
    "dt",
    "omega_mean",
    "omega_scale",
    "inertia",
    "seed",
    "dtype",
    "save_every",
    "chunk_size",
    "statistics",
)


def _directory(path: str) -> str:
    """`path` with one trailing slash (`run/` was printed as `run//`)."""
    return os.path.join(path, "")


def _file_identity(path: str) -> tuple[int, int, int] | None:
    """A file's (inode, modification time, size), or None if there is none: tells a replaced file."""
    try:
        status = os.stat(path)
    except OSError:
        return None
    return status.st_ino, status.st_mtime_ns, status.st_size


def _saved_before_interrupt(output: str, index_before: tuple[int, int, int] | None) -> str:
    """What an interrupted `simulate` left in `output`, as the index the ensemble writer keeps says.

    The writer renames a new index.json into place when it starts and after every chunk, so an index
    other than the one found before the run is this run's. Without `save_every` it saves no states
    until the end: the message must not promise any.
    """
    index_path = os.path.join(output, "index.json")
    if _file_identity(index_path) in (None, index_before):
        return ""  # interrupted before the run wrote anything
    try:
        with open(index_path, encoding="utf-8") as f:
            index = json.load(f)
        steps = [step for record in index["records"] for step in record["steps"]]
        done = (
            f"after {index['steps_done']:,} of {index['num_steps']:,} steps; "
            f"{_directory(output)} holds"
        )
        if not steps:
            return (
                f"{done} no saved states (without --save-every only the final state is saved, "
                "when the run completes)"
            )
        states = f"{len(steps):,} saved state{'s' if len(steps) > 1 else ''}"
        span = f"step {steps[0]:,}" if len(steps) == 1 else f"steps {steps[0]:,} to {steps[-1]:,}"
        return f"{done} {states}, {span} (jaxquat.load_ensemble reads them)"
    except (OSError, ValueError, KeyError, TypeError):  # not readable after all: say nothing of it
        return ""


def _check_representable(config: dict[str, Any], sources: dict[str, str], dtype: str) -> None:
    """Reject option values that overflow the run's dtype or underflow to zero in it."""
    import numpy as np

    info = np.finfo(np.dtype(dtype))
    for key in ("dt", "omega_scale", "omega_mean", "inertia"):
        value = config[key]
        if value is None:
            continue
        exact = np.asarray(value, dtype=np.float64)
        with np.errstate(over="ignore", under="ignore"):
            converted = exact.astype(info.dtype)
        if not np.all(np.isfinite(converted)):
            raise CommandLineError(
                f"{sources[key]}: {key} {_show(value)} overflows {dtype} (largest {info.max:g}); "
                f"use a smaller value{_or_float64(dtype)}"
            )
        if np.any((converted == 0) & (exact != 0)) or np.any(
            (exact != 0) & (np.abs(exact) < info.tiny)
        ):
            raise CommandLineError(
                f"{sources[key]}: {key} {_show(value)} underflows {dtype} (smallest normal "
                f"{info.tiny:g}); use a larger value{_or_float64(dtype)}"
            )


def _or_float64(dtype: str) -> str:
    """The advice to run in float64, for a run that is not in float64 already."""
    return "" if dtype == "float64" else " or --dtype float64"


def _show(value) -> str:
    if isinstance(value, (list, tuple)):
        return ",".join(_exact(v) for v in value)
    return _exact(value)


def _check_finite_results(arrays: dict[str, Any], what: str) -> None:
    """A one-line error (exit 2) when any result is NaN or infinite, instead of a bogus summary."""
    import numpy as np

    for name, array in arrays.items():
        values = np.asarray(array)
        bad = ~np.isfinite(values)
        if bad.any():
            raise CommandLineError(
                f"{name} are not finite (NaN or inf in {int(bad.sum()):,} of {values.size:,} "
                f"values) after {what}"
            )


def _print_table(rows: Sequence[tuple[str, str]]) -> None:
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"  {key:<{width}}  {value}")


# ----------------------------------------------------------------------------------------------------
# fit


# The peak memory of `jaxquat fit` (reading the CSV included), measured with /usr/bin/time -v on
# CPU: 0.70 GB for 100,000 rows, 0.84 GB for 200,000, 1.12 GB for 400,000, 2.0 GB for 1,000,000 —
# about 0.56 GB + 1.4 kB a row. The time-varying models take more: 1.42 GB for 200,000 rows with
# --model piecewise_linear --knots 10, ~4.3 kB a row (the spline is taken to be alike). Rounded up
# here, so a file the check admits fits.
_FIT_BYTES_BASE = 600 * 2**20
_FIT_BYTES_PER_ROW = {"constant": 1_600, "piecewise_linear": 4_800, "spline": 4_800}


def fit_memory_needed(rows: int, model: str = "constant") -> int:
    """The bytes `jaxquat fit --model model` needs for `rows` observations (an estimate, rounded
    up)."""
    return _FIT_BYTES_BASE + _FIT_BYTES_PER_ROW[model] * rows


# The least memory `jaxquat simulate` takes per body on the CPU, measured with /usr/bin/time -v:
# 10,000,000 bodies × 1 float32 step with --no-statistics peaked 1.75 GB above a 10-body run
# (~175 B a body); with statistics ~235 B, rigid bodies ~330 B, --save-every more. Rounded down, so
# the check refuses only runs that cannot fit: past MemAvailable the kernel kills the process
# without a word (200,000,000 bodies: SIGKILL after 160 s at 24 GB, exit status 137, nothing on
# stderr).
_SIMULATE_MIN_BYTES_PER_BODY = 160
# `demo` keeps 41 saved float32 states of every body (656 B) besides the ensemble's own: 2,000,000
# bodies peaked 4.7 GB above a 10-body demo, ~2,430 B a body; rounded down the same way (30,000,000
# bodies passed the 160 B check and were killed).
_DEMO_MIN_BYTES_PER_BODY = 1024


def check_simulate_memory(
    bodies: int, available: int | None, per_body: int = _SIMULATE_MIN_BYTES_PER_BODY
) -> None:
    """Raise the one-line "out of memory" `CommandLineError` when `bodies` bodies need more than
    `available` bytes on the CPU even at the least memory a body takes, `per_body` bytes (None:
    unknown, no check; on other devices the bodies do not live in the machine's memory)."""
    import jax

    if available is None or jax.devices()[0].platform != "cpu":
        return
    needed = per_body * bodies
    if needed > available:
        raise CommandLineError(
            f"out of memory ({bodies:,} bodies need at least {needed / 1e9:.1f} GB, "
            f"{available / 1e9:.1f} GB is available); use fewer --bodies"
        )


def _memory_available() -> int | None:
    """MemAvailable from /proc/meminfo in bytes, or None where it cannot be read (not Linux)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_fit_memory(rows: int, available: int | None, path: str, model: str = "constant") -> None:
    """Raise the one-line "out of memory" `CommandLineError` when fitting `rows` observations would
    need more than `available` bytes (None: unknown, no check). Past it the kernel kills the process
    without a word (a 1 GiB CSV holds some 15 million rows: ~24 GB)."""
    if available is None:
        return
    needed = fit_memory_needed(rows, model)
    if needed > available:
        raise CommandLineError(
            f"out of memory ({rows:,} observations need about {needed / 1e9:.1f} GB, "
            f"{available / 1e9:.1f} GB is available); fitting {path}: fewer observations"
        )


def _from_origin(origin: str | None, offset: float) -> float:
    """The double nearest the time `origin + offset` (`origin` as the file writes it, or None). The
    sum is exact (its digits are bounded by the origin's text and float64's exponents)."""
    import decimal

    if origin is None:
        return offset
    return float(_wide_context(decimal.MAX_PREC).add(_decimal(origin), decimal.Decimal(offset)))


def _first_time(first: str, t0: float) -> str:
    """t0 as the file wrote it (1e15 + 0.3 is 1000000000000000.25 as a double; a first time of 0
    stays `0` or `0.0`, not the double's repr), unless long."""
    return first if len(first) <= 40 else repr(t0)


def _knot_labels(knots: list[float], offsets: list[float]) -> list[str]:
    """Increasing `knots` with their spacing to 6 significant digits: at a Unix time `:.6g` printed
    every knot as 1.7e+09. Far from zero (beyond 10⁴ spacings, where one double may stand for
    several knots) they are written `t0 + offset` instead."""
    gap = min(b - a for a, b in zip(knots, knots[1:], strict=False))
    top = max(abs(knots[0]), abs(knots[-1]))
    if not top <= 1e4 * gap and knots is not offsets:
        return [f"t0 + {label}" for label in _knot_labels(offsets, offsets)]
    digits = 6 + max(0, math.ceil(math.log10(top / gap))) if top > 0 else 6
    return [f"{t:.{digits}g}" for t in knots]


def _cmd_fit(args: argparse.Namespace) -> int:
    # Option errors before the file is read, as option errors (the library's would name the file).
    if args.knots is not None:
        minimum = {"constant": None, "piecewise_linear": 2, "spline": 4}[args.model]
        if minimum is None:
            raise CommandLineError(
                "argument --knots: only used with --model piecewise_linear or spline"
            )
        if args.knots < minimum:
            raise CommandLineError(
                f"argument --knots: must be at least {minimum} for --model {args.model}; "
                f"got {args.knots}"
            )
    origin, times, quaternions, first = read_observations_csv(args.file)
    check_fit_memory(times.shape[0], _memory_available(), args.file, args.model)
    _setup_jax("float64")
    import numpy as np

    from ._fitting import fit_angular_velocity

    kwargs: dict[str, Any] = {"model": args.model, "frame": args.frame}
    if args.knots is not None:
        kwargs["knots"] = args.knots
    # Rows need not be unit: the fit scales each by its largest component and normalises it.
    try:
        fit = fit_angular_velocity(times, quaternions, **kwargs)
    except ValueError as e:  # what the file holds (e.g. times whose span overflows): name the file
        raise CommandLineError(f"{args.file}: {_one_line(e)}") from None
    residuals = np.degrees(np.asarray(fit.residual_angles, dtype=np.float64))
    report: dict[str, Any] = {
        "model": args.model,
        "frame": args.frame,
        "observations": int(times.shape[0]),
        # q0 is the orientation at the first observation time, not at t = 0
        "t0": _from_origin(origin, float(times[0])),
        "q0": np.asarray(fit.q0, dtype=np.float64).tolist(),
        "residual_rms_deg": float(np.sqrt(np.mean(residuals**2))),
        "residual_max_deg": float(residuals.max()),
        "converged": bool(fit.converged),
    }
    if args.model == "constant":
        omega = np.asarray(fit.omega, dtype=np.float64)
        report["omega"] = omega.tolist()
        # hypot scales: sqrt(x² + y² + z²) overflows from |ω| ~ 1e154 and underflows below 1e-154.
        report["omega_norm"] = math.hypot(*omega.tolist())
    else:
        offsets = np.asarray(fit.omega.knots, dtype=np.float64).tolist()
        report["knots"] = [_from_origin(origin, k) for k in offsets]
        report["knots_from_t0"] = offsets  # (far from zero, doubles may not tell the knots apart)
        report["omega_at_knots"] = np.asarray(fit.omega.values, dtype=np.float64).tolist()
    _check_finite_results(
        {
            "fitted values": [
                *report["q0"],
                report["residual_rms_deg"],
                report["residual_max_deg"],
                *np.ravel(report.get("omega", [])),
                report.get("omega_norm", 0.0),
                *np.ravel(report.get("omega_at_knots", [])),
            ]
        },
        f"fitting {args.file}",
    )
    if args.json:
        print(json.dumps(report, allow_nan=False))
        return 0
    if args.model == "constant":
        x, y, z = report["omega"]
        print(
            f"omega = [{x:.9g}, {y:.9g}, {z:.9g}] rad/s  (|omega| = {report['omega_norm']:.9g}, {args.frame} frame)"
        )
    else:
        print(f"omega(t) at {len(report['knots'])} knots ({args.model}, {args.frame} frame):")
        labels = _knot_labels(report["knots"], offsets)
        width = max(12, *map(len, labels))
        for t, (x, y, z) in zip(labels, report["omega_at_knots"], strict=True):
            print(f"  t = {t:<{width}} omega = [{x:.6g}, {y:.6g}, {z:.6g}] rad/s")
    print(
        f"q0 = [{', '.join(f'{v:.9g}' for v in report['q0'])}] at t0 = {_first_time(first, report['t0'])} "
        f"(the first observation)  residual rms "
        f"{report['residual_rms_deg']:.4g}°, max {report['residual_max_deg']:.4g}°, "
        f"{report['observations']} observations, converged: {report['converged']}"
    )
    return 0


# ----------------------------------------------------------------------------------------------------
# bench


def _cmd_bench(args: argparse.Namespace) -> int:
    try:
        # import_module honours sys.modules (a package attribute left by an earlier import does not).
        _bench = importlib.import_module("jaxquat._bench")
    except ImportError:
        raise CommandLineError(
            "bench: the benchmark suite (jaxquat._bench) is not installed"
        ) from None
    if args.from_command_line:
        # Large buffers on huge pages for every contender (see `relaunch_with_huge_pages`), with the
        # options given before `bench` (`--distributed`) too; before jax.distributed connects.
        _bench.relaunch_with_huge_pages(
            ["-m", "jaxquat", *args.global_args, "bench", *args.bench_args]
        )
    if _bench.will_run(list(args.bench_args)):  # (--help and bad arguments need no backend)
        _start_jax(args)
    # The suite's own default preset is quick; a --preset given here is passed on (forcing
    # "--preset quick" first made every --preset, quick included, a "given only once" error).
    return int(_bench.main(list(args.bench_args)) or 0)


# ----------------------------------------------------------------------------------------------------
# demo


def _check_png_path(path: str) -> str:
    if not path:
        raise CommandLineError("--output must name a .png file, got ''")
    if not path.lower().endswith(".png"):
        raise CommandLineError(f"--output must name a .png file, got {path!r}")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise CommandLineError(
            f"--output {path}: directory {os.path.dirname(path) or '.'} does not exist"
        )
    if os.path.isdir(path):
        raise CommandLineError(f"--output {path}: is a directory")
    if not os.access(directory, os.W_OK):
        raise CommandLineError(f"--output {path}: directory is not writable")
    # Open it now (and remove it again if it is new), before minutes of work: the checks above pass a
    # dangling symbolic link or a file system that refuses new files, found only when saving.
    existed = os.path.exists(path)  # follows a symbolic link: what `open` creates is its target
    try:
        with open(path, "ab"):
            pass
    except OSError as e:
        raise CommandLineError(f"--output {path}: {e.strerror or e}") from None
    if not existed:
        os.remove(os.path.realpath(path))
    return path


# The demo's physics: a body with principal moments (1, 2, 3) spinning about its intermediate axis
# (the tennis-racket / Dzhanibekov instability) with uncertain initial attitude and rate.
_DEMO_INERTIA = (1.0, 2.0, 3.0)
_DEMO_OMEGA = (0.01, 2.0, 0.01)  # body frame, rad/s
_DEMO_SIGMA_ATTITUDE = math.radians(0.5)
_DEMO_SIGMA_OMEGA = 0.005
_DEMO_DT = 0.02
# The fit: a satellite turning at a constant rate, attitude observed with 0.2° noise.
_FIT_OMEGA = (0.3, -0.2, 0.5)
_FIT_SIGMA = math.radians(0.2)
_FIT_COUNT = 60
_FIT_SPAN = 10.0


def _demo_ensemble(bodies: int, steps: int, seed: int, progress: bool):
    import jax
    import jax.numpy as jnp

    from ._ensemble import _angle_between, simulate_ensemble
    from ._rotation import from_rotvec

    dtype = jnp.float32
    key_q, key_w = jax.random.split(jax.random.key(seed))
    # Body 0 is the nominal body; the others are perturbed (attitude and rate).
    mask = (jnp.arange(bodies) > 0).astype(dtype)[:, None]
    attitude = _DEMO_SIGMA_ATTITUDE * mask * jax.random.normal(key_q, (bodies, 3), dtype)
    q0 = from_rotvec(attitude)
    omega0 = jnp.asarray(_DEMO_OMEGA, dtype)[
        None, :
    ] + _DEMO_SIGMA_OMEGA * mask * jax.random.normal(key_w, (bodies, 3), dtype)
    inertia = jnp.asarray(_DEMO_INERTIA, dtype)
    save_every = max(1, steps // 40)
    result = simulate_ensemble(
        q0,
        omega0,
        _DEMO_DT,
        steps,
        inertia=inertia,
        frame="body",
        method="cf4",
        save_every=save_every,
        progress=progress,
    )
    spread = jax.jit(lambda s: _angle_between(s[:, :1], s))(result.saved)
    energy0 = 0.5 * jnp.sum(inertia[None, :] * omega0 * omega0, axis=-1)
    energy = 0.5 * jnp.sum(inertia[None, :] * result.final_omega * result.final_omega, axis=-1)
    drift = jnp.max(jnp.abs(energy - energy0) / energy0)
    return result, spread, float(drift)


def _demo_fit(seed: int):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ._algebra import multiply
    from ._fitting import fit_angular_velocity
    from ._rotation import from_rotvec

    key_q, key_n = jax.random.split(jax.random.key(seed + 1))
    times = jnp.linspace(0.0, _FIT_SPAN, _FIT_COUNT, dtype=jnp.float64)
    omega = jnp.asarray(_FIT_OMEGA, jnp.float64)
    q_start = from_rotvec(jax.random.normal(key_q, (3,), jnp.float64))
    truth = multiply(from_rotvec(times[:, None] * omega[None, :]), q_start[None, :])
    noise = from_rotvec(_FIT_SIGMA * jax.random.normal(key_n, (_FIT_COUNT, 3), jnp.float64))
    observed = multiply(noise, truth)
    fit = fit_angular_velocity(times, observed)
    return np.asarray(times), np.asarray(omega), fit


def run_demo(*, bodies: int, steps: int, output: str, seed: int, progress: bool) -> int:
    """The README's main job: an ensemble, a fit of ω, a summary table and a PNG figure."""
    output = _check_png_path(output)
    started = time.perf_counter()
    _setup_jax("float64")  # the fit runs in float64; the ensemble is float32 by its inputs
    import jax
    import numpy as np

    check_simulate_memory(bodies, _memory_available(), _DEMO_MIN_BYTES_PER_BODY)
    result, spread, drift = _demo_ensemble(bodies, steps, seed, progress)
    spread_deg = np.degrees(np.asarray(spread, dtype=np.float64))
    times = np.asarray(result.times)
    times_fit, omega_true, fit = _demo_fit(seed)
    omega_fit = np.asarray(fit.omega, dtype=np.float64)
    residuals = np.degrees(np.asarray(fit.residual_angles, dtype=np.float64))
    _check_finite_results(
        {
            "attitude spreads": spread_deg,
            "final angular velocities": result.final_omega,
            "energy drifts": [drift],
            "fitted ω": omega_fit,
            "fit residuals": residuals,
        },
        f"the demo ({bodies:,} bodies, {steps:,} steps, seed {seed})",
    )

    devices = jax.devices()
    print(
        "jaxquat demo: uncertainty propagation through the tennis-racket instability\n"
        f"  {_count(bodies, 'rigid body', 'rigid bodies')}, inertia {_DEMO_INERTIA}, "
        f"body rate {_DEMO_OMEGA} rad/s "
        f"± {_DEMO_SIGMA_OMEGA}, attitude ± {math.degrees(_DEMO_SIGMA_ATTITUDE):g}°\n"
        f"  method cf4, dt {_DEMO_DT} s, {_count(steps, 'step')}, float32, "
        f"{_count(len(devices), devices[0].platform + ' device')}\n"
    )
    print(
        f"  {'t [s]':>7}  {'median':>9}  {'95 %':>9}  {'max':>9}   attitude spread from the nominal body"
    )
    rows = np.unique(np.linspace(0, len(times) - 1, min(len(times), 9)).round().astype(int))
    for i in rows:
        p50, p95 = np.percentile(spread_deg[i, 1:], (50, 95)) if bodies > 1 else (0.0, 0.0)
        print(f"  {times[i]:7.2f}  {p50:8.3f}°  {p95:8.3f}°  {spread_deg[i].max():8.3f}°")
    print(
        f"\n  energy drift (max relative, cf4): {drift:.1e}    "
        f"ensemble: {result.seconds:.1f} s compile included, "
        f"{_throughput(result.throughput)}"
    )
    error = np.linalg.norm(omega_fit - omega_true)
    print(
        f"\nfit of ω to {len(times_fit)} noisy attitude observations "
        f"(σ = {math.degrees(_FIT_SIGMA):g}°, {times_fit[-1]:g} s):\n"
        f"  true ω    [{', '.join(f'{v:+.6f}' for v in omega_true)}] rad/s\n"
        f"  fitted ω  [{', '.join(f'{v:+.6f}' for v in omega_fit)}] rad/s\n"
        f"  error {error:.2e} rad/s ({100 * error / np.linalg.norm(omega_true):.3f} %), residual rms "
        f"{np.sqrt(np.mean(residuals**2)):.3f}°, converged: {bool(fit.converged)}"
    )
    _demo_figure(output, times, spread_deg, times_fit, residuals, bodies)
    print(f"\nfigure written to {output}   (total {time.perf_counter() - started:.1f} s)")
    return 0


def _demo_figure(output, times, spread_deg, times_fit, residuals, bodies):
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(13, 3.8), layout="constrained")
    FigureCanvasAgg(figure)
    left, middle, right = figure.subplots(1, 3)
    others = spread_deg[:, 1:] if bodies > 1 else spread_deg
    floor = 1e-3
    for q, style in ((50, "-"), (95, "--"), (100, ":")):
        label = "max" if q == 100 else f"{q} %"
        left.plot(times, np.maximum(np.percentile(others, q, axis=1), floor), style, label=label)
    left.set(
        yscale="log",
        xlabel="t [s]",
        ylabel="attitude spread [deg]",
        title=f"{bodies:,} tumbling bodies",
    )
    left.legend()
    picks = np.unique(np.linspace(len(times) // 4, len(times) - 1, 4).round().astype(int))
    bins = np.logspace(-2, np.log10(180.0), 60)
    for i in picks:
        middle.hist(
            np.maximum(others[i], 1e-2), bins=bins, histtype="step", label=f"t = {times[i]:.1f} s"
        )
    middle.set(
        xscale="log", xlabel="attitude spread [deg]", ylabel="bodies", title="spread over time"
    )
    middle.legend()
    right.plot(times_fit, residuals, "o", ms=3)
    right.axhline(
        math.degrees(_FIT_SIGMA) * math.sqrt(3), color="gray", lw=0.8, label="noise rms σ√3"
    )
    right.set(xlabel="t [s]", ylabel="residual angle [deg]", title="fit of ω: residuals")
    right.legend()
    figure.savefig(output, dpi=110)


# ----------------------------------------------------------------------------------------------------
# The parser and the entry point


_NO_PROGRESS_HELP = "no progress bar (there is none anyway when stderr is not a terminal)"


def _show_progress(no_progress: bool) -> bool:
    """Whether to draw a progress bar: not with `--no-progress`, nor when stderr is not a terminal
    (a log file got the bar's carriage returns, and an error line after them was not a line)."""
    if no_progress:
        return False
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # no stream, or a closed one
        return False


def _build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=_PROG,
        description="jaxquat: differentiable JAX quaternions, orientation integrators and ensembles.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize() first (multi-host runs)",
    )
    commands = parser.add_subparsers(dest="command", metavar="{demo,simulate,fit,bench}")
    commands.required = True

    demo = commands.add_parser("demo", help="10⁵-body ensemble, a fit of ω, a table and a PNG")
    demo.add_argument("--bodies", type=_body_count, default=100_000, help="ensemble size (100000)")
    demo.add_argument("--steps", type=_step_count, default=400, help="time steps (400)")
    demo.add_argument("--output", default="jaxquat_demo.png", help="PNG path (./jaxquat_demo.png)")
    demo.add_argument("--seed", type=_seed, default=0, help="random seed 0 … 2**32-1 (0)")
    demo.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    demo.set_defaults(
        func=lambda a: run_demo(
            bodies=a.bodies,
            steps=a.steps,
            output=a.output,
            seed=a.seed,
            progress=_show_progress(a.no_progress),
        )
    )

    simulate = commands.add_parser("simulate", help="run an ensemble; write results and a summary")
    simulate.add_argument("--config", help="TOML file with any of the options below (underscores)")
    simulate.add_argument("--bodies", type=_body_count, help="number of bodies (10000)")
    simulate.add_argument("--steps", type=_step_count, help="number of steps (1000)")
    simulate.add_argument("--dt", type=_positive_float, help="time step in s (0.01)")
    simulate.add_argument(
        "--method",
        help="integrator (euler, midpoint, magnus4, magnus6, magnus8, cf4, naive, rk4)",
    )
    simulate.add_argument("--frame", choices=_FRAMES, help="frame of ω")
    simulate.add_argument(
        "--omega-scale",
        dest="omega_scale",
        type=_nonnegative_float,
        help="ω = mean + scale·N(0, I) rad/s (1.0)",
    )
    simulate.add_argument("--omega-mean", dest="omega_mean", type=_vector3, help="x,y,z in rad/s")
    simulate.add_argument(
        "--inertia",
        type=_inertia,
        help="principal moments a,b,c: simulate torque-free rigid bodies",
    )
    simulate.add_argument("--seed", type=_seed, help="random seed 0 … 2**32-1 (0)")
    simulate.add_argument("--dtype", choices=_DTYPES, help="float32 (default) or float64")
    simulate.add_argument(
        "--save-every",
        dest="save_every",
        type=_positive_int,
        help="stream the states every K steps to the output directory",
    )
    simulate.add_argument(
        "--chunk-size", dest="chunk_size", type=_positive_int, help="steps per chunk"
    )
    simulate.add_argument(
        "--output",
        help="output directory (./jaxquat_ensemble); a previous ensemble there is replaced",
    )
    simulate.add_argument(
        "--no-statistics",
        dest="statistics",
        action="store_false",
        default=None,
        help="skip the per-body total-rotation statistics",
    )
    simulate.add_argument("--no-progress", action="store_true", help=_NO_PROGRESS_HELP)
    simulate.set_defaults(func=_cmd_simulate)

    fit = commands.add_parser(
        "fit",
        help="fit ω to a CSV of t,w,x,y,z observations",
        description="Fit ω to a CSV of t,w,x,y,z observations. Prints ω (or ω at the knots), q0 — "
        "the fitted orientation at t0, the first observation's time (not at t = 0) — and the "
        "residuals; --json prints the fields model, frame, observations, t0, q0, residual_rms_deg, "
        "residual_max_deg, converged and omega, omega_norm (constant model) or knots, knots_from_t0, "
        "omega_at_knots.",
    )
    fit.add_argument("file", help="CSV file: t,w,x,y,z per line, header optional")
    fit.add_argument(
        "--model",
        choices=("constant", "piecewise_linear", "spline"),
        default="constant",
    )
    fit.add_argument("--frame", choices=("world", "body"), default="world")
    fit.add_argument("--knots", type=_positive_int, help="number of knots (time-varying models)")
    fit.add_argument("--json", action="store_true", help="print the result as JSON")
    fit.set_defaults(func=_cmd_fit)

    bench = commands.add_parser(
        "bench",
        help="the benchmark suite, quick preset unless --preset is given (further arguments go to the suite)",
    )
    bench.set_defaults(func=_cmd_bench)
    return parser


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("jaxquat")
    except metadata.PackageNotFoundError:  # run from a source tree that is not installed
        return "0+unknown"


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with `argv` (default `sys.argv[1:]`); returns the exit status.

    0 on success, 2 for a bad argument or file (one line on stderr), 130 when interrupted,
    1 for an unexpected error (one line on stderr, never a traceback). Interrupted on the command
    line (`argv` None), the process ends right after its one line (see `_exit_now`). SIGTERM keeps
    its default action (the process ends at once, status −15): a Python handler would run only
    once the main thread is back from XLA, after a compilation or a fit of many seconds.
    """
    from_command_line = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    args = None
    if from_command_line:
        sys.unraisablehook = _redelivering(sys.unraisablehook)
        # On a stdout that cannot encode ° or ω (PYTHONIOENCODING=ascii, a Windows redirect in
        # cp1252) the UnicodeEncodeError, a ValueError, ended a run that had succeeded with exit 2
        # as if an argument were bad. Such characters print as '?' instead.
        if sys.stdout is not None and hasattr(sys.stdout, "reconfigure"):
            with contextlib.suppress(ValueError, OSError, AttributeError):
                sys.stdout.reconfigure(errors="replace")
    try:
        parser = _build_parser()
        # Everything after `bench` belongs to the benchmark suite.
        bench_args: list[str] = []
        command = next((i for i, a in enumerate(argv) if not a.startswith("-")), None)
        if command is not None and argv[command] == "bench":
            argv, bench_args = argv[: command + 1], argv[command + 1 :]
        args = parser.parse_args(_join_negative_vectors(argv))
        args.bench_args = bench_args
        args.global_args = argv[:command] if command is not None else []  # e.g. --distributed
        args.from_command_line = from_command_line
        if sys.stdout is None and args.command == "fit":  # stdout closed (`>&-`): print() drops it
            raise CommandLineError("standard output is closed: there is nowhere to write the fit")
        if args.command != "bench":  # bench may relaunch itself first (see `_cmd_bench`)
            _start_jax(args)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            status = int(args.func(args) or 0)
        if _PENDING_INTERRUPT[0]:  # swallowed in a callback just before the command returned
            raise KeyboardInterrupt
        return status
    except CommandLineError as e:
        print(f"{e.prog}: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except ValueError as e:  # the library's argument checks
        print(f"{_PROG}: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `jaxquat fit f.csv | head -1`: the reader has gone; nothing to say
        _silence_stdout()
        return _BROKEN_PIPE
    except OSError as e:  # the machine's side: an unwritable output path, a full disk, ...
        where = f"{e.filename!r}: " if e.filename == "" else f"{e.filename}: " if e.filename else ""
        print(f"{_PROG}: error: {where}{e.strerror or _one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        detail = str(e) if isinstance(e, _Interrupted) else ""
        print(f"{_PROG}: interrupted{' ' if detail else ''}{detail}", file=sys.stderr)
        if from_command_line:
            _exit_now(130)
        return 130
    except SystemExit as e:  # --help / --version
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    except BaseException as e:  # noqa: BLE001 (the contract: one line, never a traceback)
        if _out_of_memory(e):  # the machine's limit, reached by the arguments: not a bug
            reason = f" ({_one_line(e)})" if _one_line(e) else ""  # a bare MemoryError says nothing
            if args is not None and getattr(args, "command", None) == "fit":
                advice = f"fitting {args.file}: fewer observations"
            elif args is not None and getattr(args, "command", None) == "demo":
                advice = "use fewer --bodies"  # demo has no --chunk-size or --save-every
            else:
                advice = "use fewer --bodies, a smaller --chunk-size or a larger --save-every"
            print(f"{_PROG}: error: out of memory{reason}; {advice}", file=sys.stderr)
            return 2
        print(f"{_PROG}: internal error: {type(e).__name__}: {_one_line(e)}", file=sys.stderr)
        return 1


def _count(number: int, singular: str, plural: str | None = None) -> str:
    """`1 step`, `1,000 steps`."""
    return f"{number:,} {singular if number == 1 else plural or singular + 's'}"


def _start_jax(args: argparse.Namespace) -> None:
    """Connect to the other processes (`--distributed`), then start JAX's backend, so that a backend
    that cannot start is one clear line: with JAX_PLATFORMS=cuda and no CUDA plugin installed, jax
    0.10 raises an AssertionError with no message from its first array."""
    import jax

    if args.distributed:
        try:
            jax.distributed.initialize()
        except (ValueError, RuntimeError) as e:
            raise CommandLineError(
                f"--distributed: jax.distributed.initialize() failed ({_one_line(e)}); it finds the "
                "other processes itself only under SLURM, Open MPI, Kubernetes or a Cloud TPU; "
                "elsewhere call jax.distributed.initialize(coordinator_address, num_processes, "
                "process_id) and jaxquat.simulate_ensemble from Python"
            ) from None
    try:
        jax.devices()
    except Exception as e:  # noqa: BLE001 (JAX's own message, when it has one, is kept)
        detail = _one_line(e) or f"{type(e).__name__} with no message"
        platforms = os.environ.get("JAX_PLATFORMS", "")
        if not platforms:
            raise CommandLineError(f"JAX could not start a backend ({detail})") from None
        raise CommandLineError(
            f"JAX could not start the backend JAX_PLATFORMS={platforms!r} asks for ({detail}); is "
            "its plugin installed (e.g. jax[cuda12]) and its device present? Unset JAX_PLATFORMS "
            "to run on the CPU"
        ) from None


# Options whose value is a vector `x,y,z` (which may start with a minus sign).
_VECTOR_OPTIONS = ("--omega-mean", "--inertia")
_NEGATIVE_VECTOR = re.compile(r"-[0-9.]")


def _join_negative_vectors(argv: list[str]) -> list[str]:
    """`--omega-mean -1,0,0` as `--omega-mean=-1,0,0`: argparse takes a value that starts with a
    minus sign and is not a plain number for an option, and said "expected one argument"."""
    joined: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] in _VECTOR_OPTIONS and i + 1 < len(argv) and _NEGATIVE_VECTOR.match(argv[i + 1]):
            joined.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            joined.append(argv[i])
            i += 1
    return joined


# The exit status of a process killed by SIGPIPE (128 + 13), as `cat`, `seq`, ... give under `head`.
_BROKEN_PIPE = 141


def _silence_stdout() -> None:
    """Point stdout at /dev/null once its reader has gone, so the flush at exit writes nothing (and
    Python prints no "Exception ignored … BrokenPipeError")."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no file descriptor (captured in tests)
        pass


def _exit_now(status: int) -> NoReturn:
    """Flush stdout and stderr and end the process with `status` at once, skipping its teardown.

    After Ctrl-C, XLA may still be running work dispatched ahead (the next chunk of an ensemble, a
    compilation), and tearing the interpreter down under it sometimes crashed (a segmentation fault,
    exit status -11 instead of 130). Nothing is lost: the ensemble writer closes every file and renames
    it into place before index.json lists it, and the streams are flushed here.
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed, or a pipe whose reader has gone
            pass
    os._exit(status)


def _out_of_memory(error: BaseException) -> bool:
    """Whether `error` is an allocation failure: NumPy's `MemoryError` or XLA's out-of-memory."""
    if isinstance(error, MemoryError):
        return True
    text = str(error)
    return type(error).__name__.endswith("RuntimeError") and (
        "Out of memory" in text or "RESOURCE_EXHAUSTED" in text
    )
