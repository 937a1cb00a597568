"""Memory of ``magnet bench soak``: every RSS sample per service, and whether it is flat after warm-up.

A soak samples each service's resident set every 0.5 s (MB), and each sample belongs to a round of the fault cycle
(``soak_plan.round_of``: 0 the quiet start, 1 the first pass of every fault, then one round per kill). Flat after
warm-up means that what the service holds does not grow with time once every bounded table and buffer has been
filled, which round 1 does. So the rule (``FLAT_RULE``) compares steady states, not single samples:

- a round's **level** is the median of its samples (what the process holds through the round; a burst of a few
  seconds does not move it), printed with the round's ``UPPER_QUANTILE`` (what it holds in its bursts);
- the reference is round 1's level (warm-up);
- flat: the level of every later round and the **end** (the median of the last ``END_WINDOW_S``, after the soak's
  quiet settling) each within ``FLAT_TOLERANCE`` of the reference (at least ``FLAT_FLOOR_MB``), above it.

The upper quantile and the highest sample are printed, not judged: a burst (bombs in flight, 2,000 connections, a
flood's backlog) lasts a few seconds, about a tenth of a round's samples, so the 90 % quantile falls on the edge of
the burst and moves with how long the machine's load made it last (a soak at 20:54 UTC: the dashboard's level 77 in
round 1 and 77-81 after, its 90 % quantile 77 in round 1, whose first 40 samples came before the first flood filled
the table, and 80-88 after, with bursts of the same height, 88-93 MB, in every round).

A leak raises a process's level from round to round: with the soak's 10-minute schedule a leak of about 1 MB a minute
or more ends above the bound (``tests/services/bench/test_soak_memory.py`` injects leaks into a soak's real samples);
a peak that comes once in a while does not move a level. Before, the rule compared the single highest sample of
every later round with the highest of rounds 0-1, so which burst a 0.5 s sample happened to catch decided the
verdict (issue 32's soaks: the compass and the dashboard `NO` in one of five runs each, with ends at or below their
warm-up).
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: a later round's level and the end are flat within this fraction (or this many MB, for the small
#: processes whose RSS moves by a few MB with what they are doing) above round 1's
FLAT_TOLERANCE, FLAT_FLOOR_MB = 0.10, 10.0
#: a round's upper level (printed): this quantile of its samples
UPPER_QUANTILE = 0.9
#: the end: the median of the samples of the last seconds (the soak's quiet settling is 20 s)
END_WINDOW_S = 10.0
#: a round with fewer samples than this (a service that was down most of it) is not judged
MIN_SAMPLES = 10
FLAT_RULE = (
    f"flat: every later round's median, and the median of the last {END_WINDOW_S:g} s, within {FLAT_TOLERANCE:.0%} "
    f"(at least {FLAT_FLOOR_MB:g} MB) above round 1's median (warm-up: the first pass of every fault)"
)


def bound_mb(reference_mb: float) -> float:
    """The highest value flat against ``reference_mb``."""
    return reference_mb + max(FLAT_TOLERANCE * reference_mb, FLAT_FLOOR_MB)


@dataclasses.dataclass
class Memory:
    """One service's samples across its restarts: ``samples`` (t_s since the soak's start, round, MB), and the
    highest in each round and while each fault was the last one inflicted."""

    high_mb: float = 0.0
    last_mb: float = 0.0
    by_round: dict[int, float] = dataclasses.field(default_factory=dict)  # the highest in each round of the cycle
    by_fault: dict[str, float] = dataclasses.field(default_factory=dict)  # the highest while each fault was last
    samples: list[tuple[float, int, float]] = dataclasses.field(default_factory=list)

    def _round_mb(self, round_no: int) -> np.ndarray:
        return np.array([mb for _, r, mb in self.samples if r == round_no])

    def levels(self, round_no: int) -> tuple[float, float] | None:
        """(median, upper quantile) of a round's samples (MB); None for a round of fewer than ``MIN_SAMPLES``."""
        mb = self._round_mb(round_no)
        if mb.size < MIN_SAMPLES:
            return None
        return float(np.median(mb)), float(np.quantile(mb, UPPER_QUANTILE))

    @property
    def warmup_levels(self) -> tuple[float, float] | None:
        """Round 1's (median, upper quantile): the reference after warm-up."""
        return self.levels(1)

    @property
    def later_levels(self) -> tuple[float, float] | None:
        """The highest median and the highest upper quantile of the rounds after round 1 (None before one)."""
        later = [lv for r in sorted(self.by_round) if r > 1 and (lv := self.levels(r)) is not None]
        return (max(m for m, _ in later), max(u for _, u in later)) if later else None

    @property
    def end_mb(self) -> float | None:
        """The median of the samples of the last ``END_WINDOW_S``."""
        if not self.samples:
            return None
        last_t = self.samples[-1][0]
        return float(np.median([mb for t, _, mb in self.samples if t >= last_t - END_WINDOW_S]))

    def flat(self) -> bool | None:
        """Flat after warm-up by ``FLAT_RULE``; None while round 1 has too few samples to judge against."""
        reference = self.warmup_levels
        if reference is None:
            return None
        bound = bound_mb(reference[0])
        later = [lv for r in sorted(self.by_round) if r > 1 and (lv := self.levels(r)) is not None]
        end = self.end_mb
        return all(median <= bound for median, _ in later) and end is not None and end <= bound

    @property
    def warmup_mb(self) -> float | None:
        """The highest sample of rounds 0 and 1 (printed beside the rule's figures)."""
        first = [mb for r, mb in self.by_round.items() if r <= 1]
        return max(first) if first else None

    @property
    def later_high_mb(self) -> float | None:
        """The highest sample after round 1 (None before a second round)."""
        later = [mb for r, mb in self.by_round.items() if r > 1]
        return max(later) if later else None

    @property
    def growth_mb(self) -> float | None:
        """The highest sample after round 1 minus the highest of rounds 0 and 1 (None before a second round)."""
        later, first = self.later_high_mb, self.warmup_mb
        return later - first if later is not None and first is not None else None


class MemoryWatch:
    """RSS samples per service (MB): every sample, the highest, the highest in each round of the cycle, the last,
    and the highest while each kind of fault was the last one inflicted (what grows when)."""

    def __init__(self) -> None:
        self.services: dict[str, Memory] = {}

    def sample(
        self, service: str, rss_mb: float | None, round_no: int, fault: str | None = None, t_s: float = 0.0
    ) -> None:
        if rss_mb is None:
            return
        memory = self.services.setdefault(service, Memory())
        memory.samples.append((t_s, round_no, rss_mb))
        memory.high_mb = max(memory.high_mb, rss_mb)
        memory.by_round[round_no] = max(memory.by_round.get(round_no, 0.0), rss_mb)
        if fault is not None:
            memory.by_fault[fault] = max(memory.by_fault.get(fault, 0.0), rss_mb)
        memory.last_mb = rss_mb


def memory_lines(memory: MemoryWatch) -> list[str]:
    """The memory part of the soak's report: per service the rule's figures, its verdict, each round's median, and
    the highest samples (by round and by fault)."""

    def pair(levels: tuple[float, float] | None) -> str:
        return "-" if levels is None else f"{levels[0]:.0f} / {levels[1]:.0f}"

    lines = [
        f"memory (RSS MB; {FLAT_RULE}):",
        "  service       warm-up: median / q90  later: highest median / q90  end  flat   median per round (0 = quiet)",
    ]
    for service, m in sorted(memory.services.items()):
        verdict = {None: "-", True: "yes", False: "NO"}[m.flat()]
        medians = " ".join("-" if (lv := m.levels(r)) is None else f"{lv[0]:.0f}" for r in sorted(m.by_round))
        end = "-" if m.end_mb is None else f"{m.end_mb:.0f}"
        lines.append(
            f"  {service:<14}{pair(m.warmup_levels):>22}{pair(m.later_levels):>29}{end:>5}  {verdict:<5}  {medians}"
        )
    lines.append("  highest sample (not judged: a burst's peak): after warm-up / later / per round")
    for service, m in sorted(memory.services.items()):
        warm, later = m.warmup_mb, m.later_high_mb
        rounds = " ".join(f"{m.by_round[r]:.0f}" for r in sorted(m.by_round))
        lines.append(
            f"  {service:<14}{'-' if warm is None else f'{warm:.0f}':>5} / {'-' if later is None else f'{later:.0f}'}"
            f"  {rounds}"
        )
    for service, m in sorted(memory.services.items()):
        if m.by_fault:
            highs = ", ".join(f"{fault} {mb:.0f}" for fault, mb in sorted(m.by_fault.items()))
            lines.append(f"  {service} highest after each fault: {highs}")
    return lines
