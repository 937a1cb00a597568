"""The schedule and the figures of ``magnet bench soak`` (no processes here: ``services.bench.soak`` runs them).

Schedule: after ``WARMUP_S`` (devices collect and calibrate), one fault every ``SPACING_S`` in the order of
``CYCLE``, round and round, until ``SETTLE_S`` before the end (the pipeline heals before the figures are read). The
cycle is three rounds; each round kills one service (calibrator, compass, edge in turn) then inflicts a flood of ids
(on Zenoh, which the compass's ROS 2 side takes too: the ROS 2 flood; and on the MAVLink edge's port at once), bombs
(the flood first: so the first round's bombs and streams meet the tables the flood filled), a router restart, a
full disk and the calibrator's database deleted (the calibrator restarted after ``DELETE_HOLD_S``); 2,000 dashboard
event streams come with the bombs. So each service lives through three rounds of every other fault.

Figures:
- calibrations lost: devices whose calibration was seen published (its ``created_ns``) and which the calibrator does
  not serve at the end, or serves an older one;
- longest heading gap: the longest time between two consecutive headings of one device (a device that stops for
  good, as an edge's devices do when it is restarted with new ids, makes no gap), with the fault it followed;
- memory: resident set (MB) per service, every 0.5 s across its restarts (``services.bench.soak_memory``): each
  round's median and 90 % quantile (round 0 is the quiet start; round 1 is the first pass of every fault, which takes
  each bounded table and buffer to its bound: the warm-up), the median of the last 10 s, and whether it is flat
  (``FLAT_RULE``: every later round's median and quantile and the end within 10 %, at least 10 MB, of round 1's);
  the highest sample of each round and after each fault are printed, not judged (a burst's peak is not a level);
- drops: every service's status ``dropped`` counters, summed over its restarts (the last answer of each run);
- status: every service's status asked every 2 s, answered within ``STATUS_LIMIT_S`` or not (``StatusTimes``; not
  counted within ``RESTART_GRACE_S`` of the service's or the router's start).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from services.bench.soak_memory import FLAT_RULE, Memory, MemoryWatch, memory_lines

__all__ = ["FLAT_RULE", "Memory", "MemoryWatch"]  # the memory's figures and rule, kept in services.bench.soak_memory

WARMUP_S = 25.0
SPACING_S = 10.0
SETTLE_S = 20.0
FULL_DISK_HOLD_S = 6.0
DELETE_HOLD_S = 5.0
MAV_FLOOD_COUNT, STREAMS, STREAMS_HOLD_S = 20_000, 2_000, 6.0
STATUS_LIMIT_S = 1.0
RESTART_GRACE_S = 6.0


@dataclasses.dataclass(frozen=True)
class Fault:
    """``kind``: kill (``target`` a service, kill -9 then start again), router (restart), bombs, flood, full-disk
    (its filesystem filled for ``hold_s``); ``at_s`` seconds after the start."""

    kind: str
    target: str = ""
    at_s: float = 0.0
    hold_s: float = 0.0

    @property
    def label(self) -> str:
        return f"{self.kind} {self.target}".strip()


#: the faults every round inflicts after its kill, and the service each round kills in turn: a service lives three
#: rounds between its kills, so memory that grows from round to round in one process shows
#: (bombs: with 2,000 dashboard event streams; flood: of ids on Zenoh, which the compass's ROS 2 side takes too, and
#: on the MAVLink edge's port at once; a round of more than six faults would not fit a 3-minute soak). The flood comes
#: before the bombs so that round 1, the warm-up's pass of every fault, is the same load as every later round: with
#: the bombs first, round 1's 2,000 streams met the dashboard's table of the edge's 11 rows and every later round's
#: the 2,000 rows a flood leaves (forgotten only after 600 s), a full first event for each stream (soak of 09:14 UTC:
#: the dashboard's highest with the bombs 89 MB in round 1, 92-99 MB later, each later one judged against 89)
ROUND = (
    Fault("flood"),
    Fault("bombs"),
    Fault("router"),
    Fault("full-disk", hold_s=FULL_DISK_HOLD_S),
    Fault("delete-db", hold_s=DELETE_HOLD_S),
)
KILLED_IN_TURN = ("calibrator", "compass", "edge")
CYCLE = tuple(fault for target in KILLED_IN_TURN for fault in (Fault("kill", target), *ROUND))
ROUND_LEN = 1 + len(ROUND)


def schedule(
    minutes: float, warmup_s: float = WARMUP_S, spacing_s: float = SPACING_S, settle_s: float = SETTLE_S
) -> list[Fault]:
    """The faults of a soak of ``minutes``, in time order (none when it is shorter than warm-up and settling)."""
    if not (math.isfinite(minutes) and minutes > 0):
        raise ValueError(f"--minutes must be a positive number, got {minutes}")
    end = minutes * 60.0 - settle_s
    out: list[Fault] = []
    at = warmup_s
    while at + CYCLE[len(out) % len(CYCLE)].hold_s <= end:
        out.append(dataclasses.replace(CYCLE[len(out) % len(CYCLE)], at_s=at))
        at += spacing_s
    return out


class HeadingGaps:
    """The longest time between consecutive headings of one device, and the fault in progress when it ended."""

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        self.longest_s = 0.0
        self.device = ""
        self.after = ""
        self.headings = 0
        self.by_fault: dict[str, float] = {}  # the longest gap that ended while each fault was the latest

    def on_heading(self, device: str, now_s: float, fault: str = "") -> None:
        self.headings += 1
        previous = self.last.get(device)
        self.last[device] = now_s
        if previous is None:
            return
        gap = now_s - previous
        if fault:
            self.by_fault[fault] = max(self.by_fault.get(fault, 0.0), gap)
        if gap > self.longest_s:
            self.longest_s, self.device, self.after = gap, device, fault


def round_of(faults_done: int) -> int:
    """The round after ``faults_done`` faults: 0 before the first (warm-up), 1 from the first kill to the next
    round's kill, and so on."""
    return 0 if faults_done == 0 else 1 + (faults_done - 1) // ROUND_LEN


class StatusTimes:
    """Per service: status queries counted (outside a restart's grace), answered within ``STATUS_LIMIT_S``, the
    slowest answer (s), the unanswered, and those not counted (within ``RESTART_GRACE_S`` of a start)."""

    def __init__(self) -> None:
        self.asked: dict[str, int] = {}
        self.in_time: dict[str, int] = {}
        self.slowest: dict[str, float] = {}
        self.unanswered: dict[str, int] = {}
        self.in_grace: dict[str, int] = {}
        self.late_after: dict[str, dict[str, int]] = {}  # per service, the faults after which one was late or missed

    def add(self, service: str, seconds: float | None, in_grace: bool, fault: str = "") -> None:
        """One query of ``service``'s status: answered after ``seconds`` (None: not answered), ``fault`` the last."""
        if in_grace:
            self.in_grace[service] = self.in_grace.get(service, 0) + 1
            return
        self.asked[service] = self.asked.get(service, 0) + 1
        if seconds is not None:
            self.slowest[service] = max(self.slowest.get(service, 0.0), seconds)
        if seconds is not None and seconds <= STATUS_LIMIT_S:
            self.in_time[service] = self.in_time.get(service, 0) + 1
            return
        if seconds is None:
            self.unanswered[service] = self.unanswered.get(service, 0) + 1
        late = self.late_after.setdefault(service, {})
        late[fault] = late.get(fault, 0) + 1

    def lines(self) -> list[str]:
        head = f"status answered within {STATUS_LIMIT_S:g} s (not counted: within {RESTART_GRACE_S:g} s of a start):"
        return [head] + [
            f"  {service}: {self.in_time.get(service, 0)} of {self.asked[service]}, slowest "
            f"{self.slowest.get(service, 0.0):.2f} s, unanswered {self.unanswered.get(service, 0)} "
            f"(not counted {self.in_grace.get(service, 0)})"
            + "".join(f"; late or missed after {f} {n}" for f, n in sorted(self.late_after.get(service, {}).items()))
            for service in sorted(self.asked)
        ]


class DropTotals:
    """Drop counters per service, summed over its runs: ``update(service, run, dropped)`` keeps the last answer of
    each run (a restarted service counts from zero)."""

    def __init__(self) -> None:
        self.runs: dict[tuple[str, int], dict[str, int]] = {}

    def update(self, service: str, run: int, dropped: Mapping[str, Any]) -> None:
        self.runs[(service, run)] = {str(k): int(v) for k, v in dropped.items()}

    def totals(self) -> dict[str, dict[str, int]]:
        out: dict[str, dict[str, int]] = {}
        for (service, _), counts in sorted(self.runs.items()):
            mine = out.setdefault(service, {})
            for cause, count in counts.items():
                mine[cause] = mine.get(cause, 0) + count
        return out


def calibrations_lost(published: Mapping[str, int], served: Mapping[str, int]) -> list[str]:
    """Devices whose published calibration (device -> created_ns) the calibrator no longer serves (device ->
    created_ns of the one it serves): none served, or an older one."""
    return sorted(d for d, created in published.items() if served.get(d, -1) < created)


def report(
    minutes: float,
    faults: list[str],
    published: Mapping[str, int],
    served: Mapping[str, int],
    gaps: HeadingGaps,
    memory: MemoryWatch,
    drops: DropTotals,
) -> str:
    """The figures as text."""
    lost = calibrations_lost(published, served)
    which = f": {', '.join(lost[:10])}" if lost else ""
    gap = f"{gaps.longest_s:.2f} s ({gaps.device or '-'}, after {gaps.after or 'no fault'})"
    lines = [
        f"soak of {minutes:g} min: {len(faults)} faults ({', '.join(faults) or 'none'})",
        f"calibrations lost: {len(lost)} of {len(published)} published{which}",
        f"longest heading gap: {gap}; {gaps.headings} heading messages",
        "  after each fault: " + (", ".join(f"{f} {s:.2f} s" for f, s in sorted(gaps.by_fault.items())) or "-"),
    ]
    lines.extend(memory_lines(memory))
    lines.append("messages dropped by cause:")
    for service, counts in drops.totals().items():
        text = ", ".join(f"{cause} {count}" for cause, count in sorted(counts.items())) or "none"
        lines.append(f"  {service}: {text}")
    return "\n".join(lines)


def stream_verdict(answered: Mapping[str, int], refused: int, late: int = 0, grace_s: float = 0.0) -> str:
    """What the dashboard's answers to the streams mean: a 503 is a designed refusal (said with a reason and
    ``Connection: close``; the page's stream retries): ``503:streams`` past the app's ``MAX_STREAMS``,
    ``503:connections`` past the dashboard's limit of connections (refused at accept, or by uvicorn); an answer
    after the hold (``late``, within ``grace_s``) is slow, not lost, and counted by its status; a connection closed
    without an answer (``none``), not answered at all within the hold and the grace (``silent``) or not accepted
    (``refused``) is a lost request."""
    served = answered.get("200", 0)
    designed = sum(n for status, n in answered.items() if status.startswith("503"))
    unanswered = answered.get("none", 0) + answered.get("silent", 0)
    lost = unanswered + refused
    other = sum(answered.values()) - served - designed - unanswered
    parts = [
        f"{served} streamed",
        (
            f"{designed} refused by design (503: the app's limit of streams {answered.get('503:streams', 0)}, "
            f"the limit of connections {answered.get('503:connections', 0)})"
        ),
        f"{late} of these answered only after the hold (within {grace_s:g} s more: slow, not lost)",
        (
            f"{lost} lost (closed without an answer {answered.get('none', 0)}, no answer within the hold and the "
            f"grace {answered.get('silent', 0)}, not accepted {refused})"
        ),
    ]
    if other:
        parts.append(f"{other} other answers")
    verdict = "every request answered" if lost == 0 and other == 0 else "NOT every request answered"
    return f"  dashboard streams: {verdict}: " + ", ".join(parts)


def front_lines(
    last: Mapping[str, Mapping[str, Any]],
    results: Mapping[str, list[dict[str, Any]]],
    deleted: Mapping[str, float],
    vehicle: tuple[str, float, int],
) -> list[str]:
    """The figures of the front door's faults: the MAVLink edge (``last``: each service's last status), its real
    vehicle (device, longest heading gap s, headings), the compass's ROS 2 side, the dashboard's streams
    (``results``: the helpers' JSON lines by kind), the deleted database (``deleted``: the soak's counts)."""
    mav, sinks = last.get("mavedge", {}), last.get("compass", {}).get("sinks", {})
    answered: dict[str, int] = {}
    for result in results.get("streams", []):
        for status, n in result.get("answered", {}).items():
            answered[status] = answered.get(status, 0) + n
    floods, d = len(results.get("mavlink", [])), deleted
    return [
        (
            f"MAVLink edge: {mav.get('devices', '?')} devices at the end (--max-port-devices 64), {floods} floods of "
            f"{MAV_FLOOD_COUNT} ids; real vehicle {vehicle[0]}: longest heading gap {vehicle[1]:.2f} s, "
            f"{vehicle[2]} headings"
        ),
        (
            f"compass ROS 2: {sinks.get('ros2_topics', '?')} devices with topics, "
            f"{sinks.get('ros2_topics_evicted', '?')} evicted (the last compass run)"
        ),
        f"dashboard streams: {len(results.get('streams', []))} rounds of {STREAMS}, answered {answered or '-'}",
        stream_verdict(
            answered,
            sum(int(r.get("refused", 0)) for r in results.get("streams", [])),
            sum(int(r.get("late", 0)) for r in results.get("streams", [])),
            max((float(r.get("grace_s", 0.0)) for r in results.get("streams", [])), default=0.0),
        ),
        (
            f"deleted database: {d['times']:g} times, store 'gone' in the status {d['gone_seen']:g} times (within "
            f"{d['seen_after_s']:.1f} s of a delete, status asked every 2 s); calibrations published while gone (lost "
            f"with the file) {d['while_gone']:g}; records that went with the file {d['with_file']:g} (the devices "
            "calibrate again)"
        ),
    ]
