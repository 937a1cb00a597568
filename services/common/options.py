"""Settings declared once: a frozen dataclass whose fields carry their option (flags, help, check, parse), from which
the argparse options are built, the parsed values read back and every value checked, in one place.

A service's settings::

    @dataclasses.dataclass(frozen=True)
    class CompassSettings:
        window: int = option(1, "--window", help="circular sliding mean over N headings", check=at_least(1))
        name: str = option("compass", "--name", help="service name for liveliness and status")
        shard: Shard = option(EVERY_DEVICE, "--shard", parse=Shard.parse, metavar="K/N", help="...")
        zenoh: ZenohSettings = ZenohSettings()  # not an option: set by the service from its own arguments

        def __post_init__(self) -> None:
            check_options(self)

    add_options(parser, CompassSettings)                       # the argparse options, "(default ...)" added
    settings = from_args(CompassSettings, args, zenoh=...)     # parse + check; ValueError naming the flag

The argparse value of an option with ``parse`` is the text the user typed (``parse`` turns it into the field's value
in ``from_args``, so a ``ValueError`` keeps its own message); a field whose default is ``False`` is a switch
(``store_true``); ``negate="--no-auto"`` makes a ``True`` default a switch that turns it off; ``repeat=True`` collects
a repeatable option into a tuple. Checks return None when the value is good, else what is wrong (the flag and the
value are added to the message); ``optional(check)`` lets None (the option not given) through.

A default that depends on the service rather than on the field (``--mode``: None, the config file's, else the
service's own, peer or router) is shown in the help with ``add_options(parser, Cls, shown={"mode": "router"})``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
Check = Callable[[Any], "str | None"]

_KEY = "magnet.option"


@dataclasses.dataclass(frozen=True)
class Option:
    """One command-line option of a settings field: its flags, help, check of the value, parse of the text."""

    flags: tuple[str, ...]
    help: str
    check: Check | None = None
    parse: Callable[[str], Any] | None = None
    metavar: str | None = None
    choices: Sequence[str] | None = None
    negate: str | None = None  # the flag that turns a True default off (e.g. --no-auto)
    repeat: bool = False
    show_default: bool = True
    group: str | None = None

    @property
    def flag(self) -> str:
        return self.negate or self.flags[0]


def option(
    default: Any,
    *flags: str,
    help: str,
    check: Check | None = None,
    parse: Callable[[str], Any] | None = None,
    metavar: str | None = None,
    choices: Sequence[str] | None = None,
    negate: str | None = None,
    repeat: bool = False,
    show_default: bool = True,
    group: str | None = None,
) -> Any:
    """A dataclass field with ``default`` that is also the command-line option ``flags`` (see the module)."""
    spec = Option(tuple(flags), help, check, parse, metavar, choices, negate, repeat, show_default, group)
    return dataclasses.field(default=default, metadata={_KEY: spec})


def options_of(cls: type) -> list[tuple[dataclasses.Field[Any], Option]]:
    """The fields of the settings class ``cls`` that are options, in declaration order."""
    return [(f, f.metadata[_KEY]) for f in dataclasses.fields(cls) if _KEY in f.metadata]


def _default_text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def add_options(
    parser: argparse.ArgumentParser | Any,
    cls: type,
    *,
    groups: dict[str, Any] | None = None,
    shown: Mapping[str, str] | None = None,
) -> None:
    """Add every option field of ``cls`` to ``parser`` (an ``ArgumentParser`` or an argument group); options with a
    ``group`` go to ``groups[group]``, made on first use. ``shown``: field name -> the default to say in its help
    where the service, not the field, sets it (the field's own default, usually None, stays the parsed value)."""
    groups = {} if groups is None else groups
    for field, spec in options_of(cls):
        target = parser
        if spec.group is not None:
            if spec.group not in groups:
                groups[spec.group] = parser.add_argument_group(spec.group)
            target = groups[spec.group]
        _add(target, field, spec, (shown or {}).get(field.name))


def _add(parser: Any, field: dataclasses.Field[Any], spec: Option, shown: str | None = None) -> None:
    default = field.default
    help_text = spec.help if shown is None else f"{spec.help} (default {shown})"
    if spec.negate is not None:
        parser.add_argument(spec.negate, dest=field.name, action="store_false", default=True, help=help_text)
        return
    if default is False:
        parser.add_argument(*spec.flags, dest=field.name, action="store_true", default=False, help=help_text)
        return
    if spec.show_default and default is not None and default != () and not spec.repeat:
        help_text = f"{help_text} (default {_default_text(default)})".replace("%", "%%")
    else:
        help_text = help_text.replace("%", "%%")
    metavar = spec.metavar
    if metavar is None and spec.choices is None:  # as argparse names it: by its flag, or its choices
        metavar = spec.flags[0].lstrip("-").replace("-", "_").upper()
    kwargs: dict[str, Any] = {"dest": field.name, "help": help_text, "metavar": metavar}
    if spec.choices is not None:
        kwargs["choices"] = spec.choices
    if spec.repeat:
        parser.add_argument(*spec.flags, action="append", default=[], **kwargs)
        return
    if spec.parse is None and isinstance(default, (int, float)) and not isinstance(default, bool):
        kwargs["type"] = type(default)
    parser.add_argument(*spec.flags, default=default, **kwargs)


def from_args(cls: type[T], args: argparse.Namespace, **others: Any) -> T:
    """The settings ``cls`` from parsed ``args`` (each option's text parsed) and ``others`` (fields that are not
    options, or values worked out from several options); ValueError naming the flag when a value is wrong."""
    values: dict[str, Any] = {}
    for field, spec in options_of(cls):
        if field.name in others:
            continue
        value = getattr(args, field.name, field.default)
        values[field.name] = _parsed(spec, value)
    return cls(**values, **others)


def _parsed(spec: Option, value: Any) -> Any:
    if spec.repeat:
        return tuple(_parsed(dataclasses.replace(spec, repeat=False), v) for v in value or ())
    if spec.parse is not None and isinstance(value, str):
        try:
            return spec.parse(value)
        except ValueError as exc:
            raise ValueError(f"{spec.flag}: {exc}") from None
    return value


def check_options(settings: Any) -> None:
    """Check every option field of ``settings`` (call from ``__post_init__``); ValueError with the flag, what is
    wrong and the value."""
    for field, spec in options_of(type(settings)):
        if spec.check is None:
            continue
        value = getattr(settings, field.name)
        values = value if spec.repeat else (value,)
        for item in values:
            problem = spec.check(item)
            if problem is not None:
                raise ValueError(f"{spec.flag} {problem}, got {item!r}")


# the usual checks: each returns what is wrong, or None


def at_least(low: int) -> Check:
    """A whole number >= ``low``."""

    def check(value: Any) -> str | None:
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            return f"must be a whole number >= {low}"
        return None

    return check


def positive(value: Any) -> str | None:
    """A finite number > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        return "must be a positive number"
    return None


def within(low: float, high: float, what: str = "a number") -> Check:
    """A number in [low, high] (None allowed: the option unset)."""

    def check(value: Any) -> str | None:
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
            return f"must be {what} in [{low:g}, {high:g}]"
        return None

    return check


def one_of(choices: Sequence[str]) -> Check:
    """One of ``choices``."""

    def check(value: Any) -> str | None:
        return None if value in choices else f"must be one of {', '.join(choices)}"

    return check


def optional(check: Check) -> Check:
    """``check``, with None (the option not given) allowed."""

    def checked(value: Any) -> str | None:
        return None if value is None else check(value)

    return checked
