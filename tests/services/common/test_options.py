"""Settings declared once: the argparse options built from a dataclass, read back, parsed and checked."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from services.common.options import (
    add_options,
    at_least,
    check_options,
    from_args,
    one_of,
    option,
    optional,
    positive,
    within,
)


def _shard(text: str) -> tuple[int, int]:
    k, n = (int(part) for part in text.split("/"))
    if not 0 <= k < n:
        raise ValueError(f"need 0 <= K < N, got {text}")
    return k, n


@dataclasses.dataclass(frozen=True)
class Example:
    window: int = option(1, "--window", help="headings averaged", check=at_least(1))
    rate: float = option(2.5, "--rate", help="per second", check=positive)
    coverage: float = option(0.8, "--min-coverage", help="fraction", check=within(0, 1, "a fraction"))
    shard: tuple[int, int] = option((0, 1), "--shard", parse=_shard, metavar="K/N", help="shard")
    auto: bool = option(True, "--auto", negate="--no-auto", help="calibrate only in sessions")
    verbose: bool = option(False, "--verbose", help="say more")
    trust: tuple[str, ...] = option((), "--trust", repeat=True, help="keys")
    other: str = "x"  # not an option

    def __post_init__(self) -> None:
        check_options(self)


def _parse(argv: list[str], **others: object) -> Example:
    parser = argparse.ArgumentParser()
    add_options(parser, Example)
    return from_args(Example, parser.parse_args(argv), **others)


def test_defaults_come_from_the_dataclass_alone() -> None:
    assert _parse([]) == Example()


def test_options_are_parsed_typed_and_collected() -> None:
    got = _parse(
        ["--window", "5", "--rate", "3", "--shard", "1/4", "--no-auto", "--verbose", "--trust", "a", "--trust", "b"]
    )
    assert got == Example(5, 3.0, 0.8, (1, 4), False, True, ("a", "b"))
    assert _parse([], other="y").other == "y"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--window", "0"], "--window must be a whole number >= 1, got 0"),
        (["--rate", "-1"], "--rate must be a positive number, got -1.0"),
        (["--min-coverage", "2"], "--min-coverage must be a fraction in [0, 1], got 2.0"),
        (["--shard", "4/4"], "--shard: need 0 <= K < N, got 4/4"),
    ],
)
def test_a_bad_value_names_its_flag(argv: list[str], message: str) -> None:
    with pytest.raises(ValueError) as exc:
        _parse(argv)
    assert str(exc.value) == message


def test_the_same_checks_hold_when_settings_are_built_in_code() -> None:
    with pytest.raises(ValueError, match="--window"):
        Example(window=0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        Example().window = 3  # type: ignore[misc]


def test_help_shows_each_default_once() -> None:
    parser = argparse.ArgumentParser()
    add_options(parser, Example)
    text = parser.format_help()
    assert "(default 1)" in text and "(default 2.5)" in text and "(default 0.8)" in text
    assert "--no-auto" in text and "--other" not in text
    assert "--min-coverage MIN_COVERAGE" in text and "--shard K/N" in text, "named by the flag, as argparse does"


@dataclasses.dataclass(frozen=True)
class Session:
    mode: str | None = option(
        None, "--mode", choices=("peer", "router"), help="mode", check=optional(one_of(("peer", "router"))), group="net"
    )
    listen: tuple[str, ...] = option((), "--listen", repeat=True, help="endpoints", group="net")

    def __post_init__(self) -> None:
        check_options(self)


def test_a_service_default_is_shown_while_the_field_keeps_none() -> None:
    parser = argparse.ArgumentParser()
    add_options(parser, Session, shown={"mode": "router"})
    assert "mode (default router)" in parser.format_help()
    assert [g.title for g in parser._action_groups if g.title == "net"] == ["net"]
    assert from_args(Session, parser.parse_args([])) == Session(None, ())
    assert from_args(Session, parser.parse_args(["--mode", "peer", "--listen", "a"])) == Session("peer", ("a",))


def test_optional_lets_none_through_and_checks_the_rest() -> None:
    assert Session().mode is None
    with pytest.raises(ValueError, match="--mode must be one of peer, router, got 'client'"):
        Session(mode="client")
