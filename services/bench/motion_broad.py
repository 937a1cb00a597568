"""``magnet bench motion --broad-dir DIR``: every BROAD trial in a directory scored as issue 20 asks.

For a user who has the BROAD recordings (CC-BY-4.0, dlaidig/broad, converted to the .npz of data/README.md, named
``broad_NN_*.npz``): each trial through the product (``magnet fit`` with the motion checks, the record applied when
accepted and none when refused, then the causal filter of ``magnet heading`` and its ``--offline`` one: the
functions of ``services.bench.motion``) against vqf 2.1.2 with its default settings on the raw data, called here
directly on the library (so a change of the product's fusion cannot move the baseline). The metric is the one of
``MotionLog.score`` (docs/design.md, "Heading in motion").

Printed: one row per trial, then for each method and filter the mean over the odd-numbered trials, the
even-numbered ones and all (develop on one half, check on the other: docs/broad-motion.md), how many fits were
accepted, and the trials where the product is worse than vqf by more than ``WORSE_BY``.
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import vqf

from magnet import frames
from magnet.attitude import fusion
from services.bench.motion import ESTIMATORS, MotionLog, load_broad, product_field

#: the fits compared with vqf
METHODS = ("ellipsoid", "gyro-ellipsoid")
FILTERS = ("causal", "offline")
#: a trial counts as worse than vqf when the product's RMS exceeds vqf's by more than this fraction (issue 20)
WORSE_BY = 0.05


def vqf_heading_deg(log: MotionLog, offline: bool) -> np.ndarray:
    """Heading (N,) deg of vqf itself with its default settings on the log's raw data (causal ``VQF`` or
    ``offlineVQF``), converted to the project's frames."""
    gyr, acc, mag = (fusion.to_vqf_frame(a) for a in (log.gyr_rads, log.acc_ms2, log.mag_ut))
    if offline:
        quat = vqf.offlineVQF(gyr, acc, mag, log.period_s)["quat9D"]
    else:
        quat = vqf.VQF(log.period_s).updateBatch(gyr, acc, mag)["quat9D"]
    heading, _, _ = frames.quaternion_to_euler(frames.ned_enu_attitude(np.asarray(quat, dtype=float)))
    return heading


@dataclasses.dataclass(frozen=True)
class TrialScore:
    """One trial: its number (the NN of broad_NN_...), name, vqf's RMS (deg) per filter, and per method the fit's
    verdict ("accepted" / "refused") and the product's RMS (deg) per filter."""

    number: int
    name: str
    vqf_deg: dict[str, float]
    verdict: dict[str, str]
    product_deg: dict[str, dict[str, float]]


def score_trial(path: Path) -> TrialScore:
    """Score one BROAD .npz (see the module docstring)."""
    log = load_broad(path)
    match = re.match(r"broad_(\d+)", log.name)
    number = int(match.group(1)) if match else 0
    vqf_deg = {name: log.score(vqf_heading_deg(log, name == "offline")) for name in FILTERS}
    verdict: dict[str, str] = {}
    product: dict[str, dict[str, float]] = {}
    for method in METHODS:
        field, verdict[method] = product_field(log, method)
        product[method] = {name: log.score(ESTIMATORS[f"fused {name}"](log, field)) for name in FILTERS}
    return TrialScore(number, log.name, vqf_deg, verdict, product)


def trial_paths(directory: str | Path) -> list[Path]:
    """The ``broad_*.npz`` files of a directory, sorted; ValueError naming the directory when there are none."""
    folder = Path(directory)
    if not folder.is_dir():
        raise ValueError(f"--broad-dir {folder}: not a directory")
    paths = sorted(folder.glob("broad_*.npz"))
    if not paths:
        raise ValueError(f"--broad-dir {folder}: no broad_*.npz files there (BROAD trials as in data/README.md)")
    return paths


def _row(score: TrialScore) -> str:
    cells = [f"{score.name[:40]:<41}", *(f"{score.vqf_deg[name]:>7.3f}" for name in FILTERS)]
    for method in METHODS:
        mark = "+" if score.verdict[method] == "accepted" else "-"
        cells += [f" {mark}", *(f"{score.product_deg[method][name]:>7.3f}" for name in FILTERS)]
    return "".join(cells)


def summary_lines(scores: Sequence[TrialScore]) -> list[str]:
    """Per method and filter: the means of vqf and the product over the odd trials, the even ones and all (with the
    change in %), accepted fits, and the trials worse than vqf by more than ``WORSE_BY``."""
    halves = {
        "odd": [s for s in scores if s.number % 2],
        "even": [s for s in scores if not s.number % 2],
        "all": list(scores),
    }
    lines = []
    for method in METHODS:
        accepted = sum(s.verdict[method] == "accepted" for s in scores)
        for name in FILTERS:
            parts = []
            for half, chosen in halves.items():
                if not chosen:
                    continue
                ours = float(np.mean([s.product_deg[method][name] for s in chosen]))
                theirs = float(np.mean([s.vqf_deg[name] for s in chosen]))
                change = 100 * (ours / theirs - 1)
                parts.append(f"{half} ({len(chosen)}) vqf {theirs:.3f} magnet {ours:.3f} ({change:+.1f} %)")
            worse = [
                f"{s.number:02d} {s.vqf_deg[name]:.3f} -> {s.product_deg[method][name]:.3f}"
                for s in scores
                if s.product_deg[method][name] > (1 + WORSE_BY) * s.vqf_deg[name]
            ]
            lines.append(f"{method:<15}{name:<8} accepted {accepted}/{len(scores)}: " + " | ".join(parts))
            lines.append(f"{'':<23}worse than vqf by > {100 * WORSE_BY:g} %: {', '.join(worse) or 'none'}")
    return lines


def run_broad_dir(directory: str | Path) -> str:
    """The table for every BROAD trial in ``directory`` (``magnet bench motion --broad-dir``)."""
    started = time.perf_counter()
    scores = [score_trial(path) for path in trial_paths(directory)]
    short = {"ellipsoid": "ell", "gyro-ellipsoid": "gyro"}
    header = f"{'trial':<41}{'vqf c':>7}{'vqf o':>7}" + "".join(
        f"{'':2}{short[method] + ' c':>7}{short[method] + ' o':>7}" for method in METHODS
    )
    lines = [
        (
            "heading RMS in motion (deg), BROAD trials: vqf 2.1.2 defaults on the raw data vs magnet fit + magnet "
            "heading (c causal, o --offline; + fit accepted and applied, - refused: raw field)"
        ),
        header,
        *(_row(score) for score in scores),
        *summary_lines(scores),
        f"benchmark time {time.perf_counter() - started:.1f} s",
    ]
    return "\n".join(lines)
