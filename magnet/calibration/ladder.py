"""The model ladder: fit what the motion identifies, from the magnetometer, the gyroscope and the Earth's field
(docs/field-calibration.md).

The correction is B = A (m - o) with A = (I + E) A0: A0 the matrix kept (the calibration in force's, else the
identity) and E symmetric. The rungs free more of (o, E):

- ``offset``: o alone (3), A0 kept;
- ``offset+scale``: o and E's diagonal (6): per-axis scale;
- ``planar``: o and E's horizontal block (xx, yy, xy) (6), for a device kept within ``PLANAR_TILT_DEG`` of level
  (car, boat, ground robot, a multirotor that only yaws): a level turn shows the horizontal hard and soft iron, the
  vertical offset comes from the expected dip;
- ``ellipsoid`` (o and all of E, 9), only when the motion identifies it; above it the methods of the sphere
  (``ellipsoid``, ``gyro-ellipsoid`` with the magnetometer's lag: ``magnet.calibration.choose``).

One least-squares problem, three kinds of evidence, each block weighted by its own residual spread (re-estimated
once, so that no constant is tuned to a file):

- magnitude: |A (m - o)| = F, F the expected |B| (WMM; else the cloud's own radius);
- vertical: d . A (m - o) = v, d the down direction in body axes from the gyroscope + accelerometer filter (or the
  quasi-static samples); v the vertical field, a parameter held near F sin(dip) by the WMM's dip as a prior (free
  when the dip is unknown);
- the gyroscope (Kok and Schon 2016; Vasconcelos et al. 2011): over a window s..e of at most ``gyro_ellipsoid``'s
  length, the field is constant in the earth frame while the body turns, b(e) = P^T b(s), P the turn the gyroscope
  measured: linear in o, and it identifies o from turns about two axes, or its horizontal part from yaw alone.

The identifiability rule (``identified_deg``): the information matrix J^T J (weighted) of a rung's free parameters at
its solution gives their covariance (times ``CORRELATION_S`` / period: neighbouring samples are not independent);
the largest eigenvalue of the offset's block (seen through the mean horizontal projector in body axes: an offset
error along the vertical bends no heading) over the horizontal field, and of E's block, turned into degrees, is the
heading error the rung's own noise leaves. The richest rung whose figure is within ``IDENTIFIED_DEG`` is fitted;
none: FitError. Pure numpy.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from magnet.calibration.base import FitError
from magnet.calibration.gyro_ellipsoid import skew
from magnet.calibration.rungs import (
    ISO,
    Evidence,
    Rung,
    matrix_of,
    mean_down,
)

#: a rung is identified when the heading error its parameters' noise leaves is within this (deg)
IDENTIFIED_DEG = 1.5
#: samples closer than this in time are counted as one for the covariance (s): a walk's or a car's attitude and its
#: residual errors change over a fraction of a second, not sample by sample
CORRELATION_S = 0.2
#: at most this many samples enter the magnitude and vertical blocks (every k-th: neighbours carry little more)
MAX_ROWS = 2500
#: the WMM dip's prior on the vertical field: one standard deviation, in uT (local anomalies, the model's error)
VERTICAL_PRIOR_UT = 1.0
#: a fit whose vertical field ends this far from the WMM's is not identified (uT): the data moved it off its prior,
#: which only a local minimum far from the truth or a disturbed place does (a car's 35 s without a turn: 47 uT off)
VERTICAL_LIMIT_UT = 3.0
#: the prior on each of E's parameters (one standard deviation): a magnetometer's gains and soft iron stay within a
#: few % of the identity (a phone's 4 %, ``SensorErrors.phone``), and |B| is the WMM's; without it a short arc is fitted
#: as well by a far centre and a shrunken matrix (a robot's 20 s: A = 0.23 I, the offset 174 uT off)
E_PRIOR = 0.1
#: the prior on the gyroscope's bias (rad/s, one standard deviation: a phone's reaches 0.5 deg/s, 0.009 rad/s)
BIAS_PRIOR_RADS = 0.02
#: least spread of a block's residuals (uT): the magnetometer's noise floor, so that a perfect block is not infinite
MIN_SIGMA_UT = 0.2
#: samples whose magnitude residual exceeds this many block spreads are left out after the first pass
OUTLIER_SIGMAS = 4.0
#: Gauss-Newton iterations per pass; steps shorter than STEP_TOL (uT, or relative for E) end it early
ITERATIONS = 15
STEP_TOL = 1e-6


@dataclasses.dataclass(frozen=True)
class RungFit:
    """A rung's solution: offset (3,), matrix A (3, 3), the vertical field v (uT), the heading error its noise
    leaves (deg, ``identified_deg``), the information's eigenvalues (normalised: per parameter, in uT^-2 for o
    and per unit^2 for E), the residual spread of each block (uT), samples used."""

    rung: Rung
    offset: np.ndarray
    matrix: np.ndarray
    vertical_ut: float
    identified_deg: float
    eigenvalues: tuple[float, ...]
    sigma_ut: dict[str, float]
    used: int
    #: when ``identified_deg`` is over IDENTIFIED_DEG: what the motion left unknown and the motion that would show
    #: it, in words (``unidentified``); "" otherwise
    unidentified: str = ""


@dataclasses.dataclass(frozen=True)
class _Point:
    """The model at one parameter vector x = (o (3), E free, v, beta (3)): A (3, 3), b = A (m - o) (N, 3),
    db/dE (N, 3, free), v (uT) and the gyroscope's bias beta (3,) rad/s."""

    a: np.ndarray
    b: np.ndarray
    db_de: np.ndarray
    v: float
    beta: np.ndarray

    def rows(self, grad_b: np.ndarray, idx: np.ndarray, dv: float, sigma: float) -> np.ndarray:
        """The weighted Jacobian rows (R, P) of residuals whose gradient in b is grad_b (R, 3) at rows idx."""
        je = np.einsum("ni,nik->nk", grad_b, self.db_de[idx])
        return np.hstack([-grad_b @ self.a, je, np.full((len(idx), 1), dv), np.zeros((len(idx), 3))]) / sigma


def _point(ev: Evidence, rung: Rung, x: np.ndarray) -> _Point:
    free = len(rung.e_free)
    e = np.zeros(10)
    e[list(rung.e_free)] = x[3 : 3 + free]
    u = (ev.mag - x[:3]) @ ev.matrix0.T  # A0 (m - o)
    b = u + u @ np.einsum("k,kij->ij", e, ev.basis).T
    db_de = np.einsum("kij,nj->nik", ev.basis[list(rung.e_free)], u)  # db/dE_k = G_k u; db/do = -A
    return _Point(matrix_of(ev, e), b, db_de, float(x[3 + free]), x[4 + free : 7 + free])


def _gyroscope_block(
    ev: Evidence, point: _Point, rows: np.ndarray, sigma: float
) -> tuple[np.ndarray, Callable[[], np.ndarray]] | None:
    """The windows' residuals (3 M,) and a function making their Jacobian (3 M, P), weighted; None without windows.
    With w = P^T b(s), P the turn the gyroscope measured over the window (dt long) and beta its bias, the true turn is
    about P exp(-[beta dt]x): the residual is b(e) - w + dt [w]x beta (a phone's bias reaches 0.5 deg/s)."""
    if ev.spans is None or ev.period_s is None:
        return None
    starts, ends, back = ev.spans
    ok = rows[starts] & rows[ends]
    s_, e_, p_ = starts[ok], ends[ok], back[ok]
    if not len(s_):
        return None
    w = np.einsum("nij,nj->ni", p_, point.b[s_])
    dt = ((e_ - s_) * ev.period_s)[:, None, None]
    w_cross = skew(w) * dt
    r = (point.b[e_] - w + np.einsum("nij,j->ni", w_cross, point.beta)).reshape(-1)

    def jacobian() -> np.ndarray:
        jo = (-(np.eye(3)[None] - p_) @ point.a).reshape(-1, 3)
        je = (point.db_de[e_] - np.einsum("nij,njk->nik", p_, point.db_de[s_])).reshape(len(r), -1)
        return np.hstack([jo, je, np.zeros((len(r), 1)), w_cross.reshape(-1, 3)]) / sigma

    return r / sigma, jacobian


def _priors(ev: Evidence, rung: Rung, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The priors' residuals and Jacobian rows: v near the WMM's (when known), E near zero, beta near zero."""
    free = len(rung.e_free)
    size = 3 + free + 4
    scales = [(3 + k, E_PRIOR) for k in range(free)] + [(4 + free + k, BIAS_PRIOR_RADS) for k in range(3)]
    rows_r = [x[index] / scale for index, scale in scales]
    rows_j = [np.eye(size)[index] / scale for index, scale in scales]
    if ev.vertical_ut is not None:
        rows_r.append((x[3 + free] - ev.vertical_ut) / VERTICAL_PRIOR_UT)
        rows_j.append(np.eye(size)[3 + free] / VERTICAL_PRIOR_UT)
    return np.array(rows_r), np.array(rows_j)


def _residuals(
    ev: Evidence, rung: Rung, x: np.ndarray, rows: np.ndarray, sigma: dict[str, float]
) -> tuple[np.ndarray, Callable[[], np.ndarray]]:
    """(weighted residuals (R,), a function making their weighted Jacobian (R, P): a refused trial needs none) at x = (o
    (3), E free, v, beta (3)) over the used rows: the magnitude, the vertical field, the gyroscope's windows, priors."""
    point = _point(ev, rung, x)
    idx = np.flatnonzero(rows)
    norm = np.linalg.norm(point.b[idx], axis=1)
    blocks_r = [(norm - ev.field_ut) / sigma["magnitude"]]
    blocks_j: list[Callable[[], np.ndarray]] = []
    blocks_j.append(lambda: point.rows(point.b[idx] / norm[:, None], idx, 0.0, sigma["magnitude"]))
    if ev.down is not None:
        known = idx[np.all(np.isfinite(ev.down[idx]), axis=1)]
        d = ev.down[known]
        blocks_r.append((np.einsum("ni,ni->n", d, point.b[known]) - point.v) / sigma["vertical"])
        blocks_j.append(lambda: point.rows(d, known, -1.0, sigma["vertical"]))
    gyroscope = _gyroscope_block(ev, point, rows, sigma["gyroscope"])
    if gyroscope is not None:
        blocks_r.append(gyroscope[0])
        blocks_j.append(gyroscope[1])
    prior_r, prior_j = _priors(ev, rung, x)
    return np.concatenate([*blocks_r, prior_r]), lambda: np.vstack([*(block() for block in blocks_j), prior_j])


def _block_spreads(ev: Evidence, rung: Rung, x: np.ndarray, rows: np.ndarray) -> dict[str, float]:
    """Each block's RMS residual (uT), at least MIN_SIGMA_UT."""
    point = _point(ev, rung, x)
    b = point.b
    out = {"magnitude": float(np.sqrt(np.mean((np.linalg.norm(b[rows], axis=1) - ev.field_ut) ** 2)))}
    if ev.down is not None:
        known = rows & np.all(np.isfinite(ev.down), axis=1)
        if known.any():
            out["vertical"] = float(np.sqrt(np.mean((np.einsum("ni,ni->n", ev.down[known], b[known]) - point.v) ** 2)))
    gyroscope = _gyroscope_block(ev, point, rows, 1.0)
    if gyroscope is not None:
        out["gyroscope"] = float(np.sqrt(np.mean(gyroscope[0] ** 2)))
    return {k: max(out.get(k, 1.0), MIN_SIGMA_UT) for k in ("magnitude", "vertical", "gyroscope")}


def _gram(j: np.ndarray) -> np.ndarray:
    """J^T J (P, P) of a tall (R, P) matrix, by einsum: a threaded BLAS product of so few columns spends more time
    handing out rows than multiplying on a shared machine (measured: 1 s instead of 0.05 s per fit under load)."""
    return np.einsum("ri,rj->ij", j, j)


def _solve(ev: Evidence, rung: Rung, x: np.ndarray, rows: np.ndarray, sigma: dict[str, float]) -> np.ndarray:
    """Gauss-Newton with a little Levenberg-Marquardt damping from x; J and J^T J made only at points stepped from."""
    damping = 1e-6
    r, jacobian = _residuals(ev, rung, x, rows, sigma)
    j = jacobian()
    cost = float(np.einsum("r,r->", r, r))
    normal, gradient = _gram(j), -np.einsum("ri,r->i", j, r)
    for _ in range(ITERATIONS):
        step = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), gradient)
        trial = x + step
        r2, jacobian = _residuals(ev, rung, trial, rows, sigma)
        cost2 = float(np.einsum("r,r->", r2, r2))
        if cost2 <= cost:
            x, r, cost = trial, r2, cost2
            damping = max(damping / 10, 1e-9)
            if np.max(np.abs(step[:3])) < STEP_TOL * ev.field_ut and np.max(np.abs(step[3:]), initial=0) < STEP_TOL:
                break
            j = jacobian()
            normal, gradient = _gram(j), -np.einsum("ri,r->i", j, r)
        else:
            damping *= 10
            if damping > 1e6:
                break
    return x


def _identified_deg(ev: Evidence, rung: Rung, j: np.ndarray, step: int) -> tuple[float, tuple[float, ...], str]:
    """(heading error the parameters' noise leaves, deg; the information's eigenvalues; what is least identified, in
    words: ``_weakest``) from the weighted Jacobian of rows ``step`` samples apart."""
    free = 3 + len(rung.e_free)
    info = _gram(j)
    inflation = 1.0 if ev.period_s is None else max(CORRELATION_S / (ev.period_s * step), 1.0)
    values, vectors = np.linalg.eigh(info[:free, :free])
    eigen = tuple(float(v) for v in values)
    try:
        cov = np.linalg.inv(info) * inflation
    except np.linalg.LinAlgError:
        return math.inf, eigen, _weakest(ev, rung, vectors[:, 0])
    if not np.all(np.isfinite(cov)) or values[0] <= 0:
        return math.inf, eigen, _weakest(ev, rung, vectors[:, 0])
    weight = _horizontal_weight(ev)  # an offset error along the vertical bends no heading
    offset_values, offset_vectors = np.linalg.eigh(weight @ cov[:3, :3] @ weight)
    offset = float(offset_values[-1]) / ev.horizontal_ut**2
    shape = [3 + k for k, index in enumerate(rung.e_free) if index != ISO]  # heading does not see the isotropic
    matrix = float(np.linalg.eigvalsh(cov[np.ix_(shape, shape)])[-1]) if shape else 0.0
    weakest = np.zeros(free)
    if offset >= matrix:
        weakest[:3] = offset_vectors[:, -1]
    else:
        weakest[3:] = 1.0
    return math.degrees(math.sqrt(max(offset, 0.0) + max(matrix, 0.0))), eigen, _weakest(ev, rung, weakest)


#: what a refusal of a rung asked for by name (``--method NAME``) adds to what the motion leaves unknown
AUTO_HINT = ", or let --method auto fit what the motion identifies"


def _body(vector: np.ndarray) -> str:
    return "(" + ", ".join(f"{value:+.2f}" for value in vector) + ")"


def _weakest(ev: Evidence, rung: Rung, direction: np.ndarray) -> str:
    """What the motion leaves unknown, in words, and the motion that would show it: ``direction`` (3 + free,) in the
    rung's parameters (o, E free), its offset part in body axes. Along the device's mean vertical (within 45 deg): a
    tilt shows it; across it: more headings; in E: turns through more headings and tilts, or fewer parameters."""
    offset = direction[:3]
    if float(np.linalg.norm(offset)) < 0.5 * float(np.linalg.norm(direction)):
        return (
            f"{rung.name}'s soft iron ({', '.join(rung.estimated[1:]) or 'scale'}): turn the device through more "
            "headings and tilts"
        )
    return offset_direction(ev, offset / float(np.linalg.norm(offset)))


def offset_direction(ev: Evidence, unit: np.ndarray, note: str = "") -> str:
    """The offset's direction ``unit`` (3,) in body axes, in words, with what would show it; ``note`` (why it is
    not identified) follows the direction."""
    down = mean_down(ev.down)
    unit = unit if float(unit @ down) >= 0 else -unit
    if ev.down is not None and float(unit @ down) >= math.cos(math.radians(45.0)):
        return (
            f"the offset along the device's mean vertical (body axes {_body(down)}){note}: a device held near one "
            "attitude cannot tell it from its gain; tilt it (roll and pitch by 30 deg or more while turning)"
            + (
                ", or give the place (--location: its dip then holds the vertical field)"
                if ev.vertical_ut is None
                else ""
            )
        )
    return (
        f"the offset along body axes {_body(unit)}{note}: turn the device through more headings (a full turn or more)"
    )


def _horizontal_weight(ev: Evidence) -> np.ndarray:
    """W (3, 3): the square root of the body-frame horizontal projector averaged over the samples,
    I - mean(d d^T) (I where down is unknown): an offset error e bends heading by about |W e| / Bh."""
    if ev.down is None:
        return np.eye(3)
    down = ev.down[np.all(np.isfinite(ev.down), axis=1)]
    if len(down) == 0:
        return np.eye(3)
    projector = np.eye(3) - down.T @ down / len(down)
    values, vectors = np.linalg.eigh(projector)
    return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T


def fit_rung(ev: Evidence, rung: Rung, start: np.ndarray, rows: np.ndarray | None = None) -> RungFit:
    """Fit ``rung`` from the offset ``start`` (3,) over ``rows`` (N,) bool (None: all): a first pass with unit
    spreads, the spreads re-estimated and gross outliers (OUTLIER_SIGMAS) left out, a second pass."""
    used = np.ones(len(ev.mag), dtype=bool) if rows is None else rows.copy()
    step = max(1, math.ceil(int(used.sum()) / MAX_ROWS))
    whole = ev
    if step > 1:  # every step-th sample, and the ends of the gyroscope's windows among the rows
        thin = np.zeros(len(used), dtype=bool)
        thin[::step] = True
        if ev.spans is not None:
            ok = used[ev.spans[0]] & used[ev.spans[1]]
            thin[ev.spans[0][ok]] = thin[ev.spans[1][ok]] = True
        ev, used = ev.only(used & thin)
    v0 = ev.vertical_ut if ev.vertical_ut is not None else 0.0
    x = np.concatenate([start, np.zeros(len(rung.e_free)), [v0], np.zeros(3)])
    sigma = {"magnitude": 1.0, "vertical": 2.0, "gyroscope": 2.0}
    x = _solve(ev, rung, x, used, sigma)
    sigma = _block_spreads(ev, rung, x, used)
    free = len(rung.e_free)
    e = np.zeros(10)
    e[list(rung.e_free)] = x[3 : 3 + free]
    b = (ev.mag - x[:3]) @ matrix_of(ev, e).T
    used &= np.abs(np.linalg.norm(b, axis=1) - ev.field_ut) <= OUTLIER_SIGMAS * sigma["magnitude"]
    if used.sum() < 30:
        raise FitError(f"{rung.name}: fewer than 30 samples agree with one field: keep away from iron while moving")
    x = _solve(ev, rung, x, used, sigma)
    sigma = _block_spreads(ev, rung, x, used)
    j = _residuals(ev, rung, x, used, sigma)[1]()
    identified, eigen, weakest = _identified_deg(ev, rung, j, step)
    if ev.vertical_ut is not None and abs(float(x[3 + free]) - ev.vertical_ut) > VERTICAL_LIMIT_UT:
        identified = math.inf  # a minimum far from the WMM's dip: the motion did not pin the offset down
        away = float(x[3 + free]) - ev.vertical_ut
        note = f", its vertical field {away:+.1f} uT from the WMM's dip (limit {VERTICAL_LIMIT_UT:g})"
        weakest = offset_direction(ev, mean_down(ev.down), note)
    e = np.zeros(10)
    e[list(rung.e_free)] = x[3 : 3 + free]
    unidentified = weakest if identified > IDENTIFIED_DEG else ""
    return RungFit(
        rung,
        x[:3].copy(),
        matrix_of(whole, e),
        float(x[3 + free]),
        identified,
        eigen,
        sigma,
        int(used.sum()),
        unidentified,
    )


def first_offset(ev: Evidence, rows: np.ndarray | None = None) -> np.ndarray:
    """A starting offset (3,): linear least squares of what is linear in o with A0 kept (the gyroscope's windows
    and the vertical field), with the sphere of radius F; the kept offset where that is undetermined."""
    used = np.ones(len(ev.mag), dtype=bool) if rows is None else rows
    a0 = ev.matrix0
    rows_j, rows_r = [], []
    m = ev.mag[used]
    # the sphere |m - o|^2 = R^2 in A0's frame: 2 u.o' + k = |u|^2, o' = A0 o, k = R^2 - |o'|^2 (algebraic)
    u = m @ a0.T
    design = np.hstack([2 * u, np.ones((len(u), 1))])
    scale = float(np.median(np.linalg.norm(u - np.median(u, axis=0), axis=1))) or 1.0
    rows_j.append(design / scale)
    rows_r.append(np.einsum("ij,ij->i", u, u) / scale)
    if ev.spans is not None:
        starts, ends, back = ev.spans
        ok = used[starts] & used[ends]
        if ok.any():
            # A0 m(e) - o' = P^T (A0 m(s) - o')  ->  (P^T - I) o' = P^T u(s) - u(e)
            ue, us = ev.mag[ends[ok]] @ a0.T, ev.mag[starts[ok]] @ a0.T
            lhs = (back[ok] - np.eye(3)[None]).reshape(-1, 3)
            rhs = (np.einsum("nij,nj->ni", back[ok], us) - ue).reshape(-1)
            rows_j.append(np.hstack([lhs, np.zeros((len(lhs), 1))]) * 10.0)
            rows_r.append(rhs * 10.0)
    solution, *_ = np.linalg.lstsq(np.vstack(rows_j), np.concatenate(rows_r), rcond=None)
    offset = np.linalg.solve(a0, solution[:3])
    if not np.all(np.isfinite(offset)):
        return ev.offset0.copy()
    return offset
