"""Types of the compiled kernels (magnet/_kernels.c, where each is documented)."""

from typing import Any

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
def vqf_attitudes(
    raw: np.ndarray,
    fused: np.ndarray,
    quat: np.ndarray,
    rotation: np.ndarray | None,
    down: np.ndarray,
    heading: np.ndarray,
    pitch: np.ndarray,
    roll: np.ndarray,
) -> None: ...
def sigma_direct(
    field: np.ndarray,
    acc: np.ndarray,
    down_fused: np.ndarray,
    fused: np.ndarray,
    flags: np.ndarray,
    expected: np.ndarray,
    residual: np.ndarray,
    disturbed_bits: int,
    max_dip_rad: float,
    uncalibrated_fraction: float,
    unlevel_rad: float,
    gravity: float,
    tan_dip: np.ndarray,
    field_rad: np.ndarray,
    tilt: np.ndarray,
    variance: np.ndarray,
) -> None: ...
def sigma_degrees(
    variance: np.ndarray,
    tilt: np.ndarray,
    max_sigma_deg: float,
    unlevel_deg: float,
    min_tilt_deg: float,
    heading_deg: np.ndarray,
    tilt_deg: np.ndarray,
) -> None: ...
def turn_about_down(quat: np.ndarray, angle_deg: np.ndarray, out: np.ndarray) -> None: ...
def row_faults(arr: np.ndarray, limit: float, absent_rows: bool, nonfinite: np.ndarray, beyond: np.ndarray) -> None: ...
def tilt_heading(field: np.ndarray, acc: np.ndarray, heading: np.ndarray | None, dip: np.ndarray | None) -> None: ...
def correct_field(
    mag: np.ndarray, offsets: np.ndarray, matrices: np.ndarray, bounds: np.ndarray, out: np.ndarray
) -> None: ...
def horizontal_force(rotation: np.ndarray, acc: np.ndarray, scale: float, out: np.ndarray) -> None: ...
def column_checks(matrix: np.ndarray, out: np.ndarray) -> None: ...
def format_rows(matrix: np.ndarray, decimals: bytes) -> bytes: ...
def vqf_bind(path: str) -> None: ...
def vqf_probe(filter: object) -> dict[str, Any]: ...
def vqf_travelled(filter: object, seconds: float) -> None: ...
def aided_layout() -> dict[str, int]: ...
def aided_update(
    filter: object,
    settings: np.ndarray,
    state: np.ndarray,
    fix_times: np.ndarray,
    fix_values: np.ndarray,
    pending: np.ndarray,
    t: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    field: np.ndarray,
    vel: np.ndarray,
    quat: np.ndarray,
    disturbed: np.ndarray,
) -> None: ...
def fixes_observe(
    meta: np.ndarray,
    times: np.ndarray,
    values: np.ndarray,
    t: np.ndarray,
    vel: np.ndarray,
    delay_s: float,
    max_fixes: int,
) -> None: ...
def fixes_arrivals(meta: np.ndarray, vel: np.ndarray, out: np.ndarray) -> None: ...
def fixes_standing(
    meta: np.ndarray,
    times: np.ndarray,
    values: np.ndarray,
    start_s: float,
    end_s: float,
    half_window_s: float,
    max_speed: float,
) -> int: ...
def drift_update(
    drift: np.ndarray,
    figures: np.ndarray,
    t_s: float,
    count: float,
    heading_rad: float,
    horizontal: float,
    vertical: float,
    disturbed: bool,
    up: np.ndarray,
    tilt_rad: float,
) -> tuple[float, float, float]: ...
def explained_update(store: np.ndarray, left_ms2: float, seconds: float, time_s: float) -> float: ...
def vertical_correction(
    store: np.ndarray, delta: float, up: np.ndarray, seconds: float, disturbed: bool
) -> tuple[float, float, float]: ...
def vehicle_tau_acc(residual_ms2: float, bias_sigma_rads: float, half_window_s: float, gravity: float) -> float: ...
def horizontal_bias_sigma(bias_p: np.ndarray, up: np.ndarray) -> float: ...
def gate_layout() -> dict[str, int]: ...
def gate_update(
    settings: np.ndarray,
    state: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    start: np.ndarray,
    bias: np.ndarray,
    fed: np.ndarray,
    gated: np.ndarray,
) -> bool: ...
def gated_run(
    filter: object,
    settings: np.ndarray,
    state: np.ndarray,
    gyr: np.ndarray,
    acc: np.ndarray,
    field: np.ndarray | None,
    quat6: np.ndarray | None,
    quat9: np.ndarray,
    rest: np.ndarray,
    disturbed: np.ndarray,
    heading_settings: np.ndarray | None,
    heading_state: np.ndarray | None,
) -> None: ...
def fuse_rows(
    filter: object,
    settings: np.ndarray,
    state: np.ndarray,
    watch: tuple[Any, ...] | None,
    gyr: np.ndarray,
    acc: np.ndarray,
    field: np.ndarray,
    lo: int,
    hi: int,
    quat9: np.ndarray,
    disturbed: np.ndarray,
    heading_settings: np.ndarray | None,
    heading_state: np.ndarray | None,
) -> None: ...
def first_take(
    field: np.ndarray,
    low2: float,
    high2: float,
    min_judged_s: float,
    max_share: float,
    state: np.ndarray,
    out: np.ndarray,
) -> tuple[int, int]: ...
def heading_gate_layout() -> dict[str, int]: ...
def heading_gate_update(
    settings: np.ndarray,
    state: np.ndarray,
    gyr: np.ndarray,
    field: np.ndarray,
    start: np.ndarray,
    bias: np.ndarray,
    delta: float,
    k_mag_init: float,
    fed: np.ndarray,
    flags: np.ndarray,
) -> bool: ...
def bias_drift(
    t_ns: np.ndarray,
    trusted: np.ndarray,
    bounds: np.ndarray,
    slot: np.ndarray,
    untrusted: np.ndarray,
    bias: np.ndarray,
    slots: np.ndarray,
    drift: np.ndarray,
) -> None: ...
def batch_figures(
    bounds: np.ndarray,
    t_ns: np.ndarray,
    fused: np.ndarray,
    trusted: np.ndarray,
    tan_dip: np.ndarray,
    horizontal: np.ndarray,
    out: np.ndarray,
) -> None: ...
def gyro_rows(
    gyr: np.ndarray,
    acc: np.ndarray,
    field: np.ndarray,
    limit: float,
    present: np.ndarray,
    finite: np.ndarray,
    saturated: np.ndarray,
    usable: np.ndarray,
) -> None: ...
def disturbance_bits(
    field: np.ndarray,
    acc: np.ndarray | None,
    expected: np.ndarray | None,
    dip: np.ndarray | None,
    expected_dip: np.ndarray | None,
    field_tol_pct: float,
    dip_tol_deg: float,
    tiny: float,
    flags: np.ndarray,
) -> None: ...
