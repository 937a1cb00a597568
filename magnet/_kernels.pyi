"""Types of the compiled kernels (magnet/_kernels.c, where each is documented)."""

import numpy as np

def carry_forward(start: np.ndarray, gyr: np.ndarray, bias: np.ndarray, period_s: float, out: np.ndarray) -> None: ...
def quaternion_product(
    p: np.ndarray, q: np.ndarray, out: np.ndarray, conjugate_p: bool = False, normalise: bool = False
) -> None: ...
def into_body(quat_vqf: np.ndarray, a_ned: np.ndarray, out: np.ndarray) -> None: ...
def piece_figures(
    quat6d: np.ndarray, field: np.ndarray, acc: np.ndarray, gravity: float
) -> tuple[float, float, float, float, float, float, float]: ...
def centred_difference(
    times: np.ndarray, values: np.ndarray, t: np.ndarray, half_window: float, out: np.ndarray
) -> None: ...
def drift_step(
    x: np.ndarray,
    p: np.ndarray,
    dt: float,
    tau_s: float,
    up: np.ndarray,
    q_diag: np.ndarray,
    z: float,
    noise: float,
    update: bool,
) -> None: ...
def advance_field(field: np.ndarray, gyr: np.ndarray, lags: np.ndarray, out: np.ndarray) -> None: ...
def watch_update(
    field: np.ndarray,
    gyr: np.ndarray,
    flagged: np.ndarray,
    state: np.ndarray,
    levels: np.ndarray,
    ring: np.ndarray,
    pending: np.ndarray,
    calm: np.ndarray,
    widths: np.ndarray,
    floors: np.ndarray,
    period_s: float,
    smooth: int,
    hold: int,
    block: int,
    relative: float,
    field_tol_pct: float,
    learn_s: float,
    level_tau_s: float,
    max_reject_s: float,
    turn_floor_rad: float,
) -> None: ...
def format_rows(matrix: np.ndarray, decimals: bytes) -> bytes: ...
