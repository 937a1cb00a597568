"""Honeywell HMC1043: a three-axis AMR bridge with analog outputs (seed 001), read through an ADC.

There is no I2C chip to talk to, so this "driver" replays recorded bridge outputs, either in volts or in ADC counts,
and converts them to the field:

    volts = (counts - zero_counts) * vref_v / 2**adc_bits              (counts only)
    field_ut = volts / (amplifier_gain * supply_v * sensitivity_mv_per_v_per_gauss / 1000) * 100

The datasheet's typical sensitivity is 1.0 mV/V/gauss. Rows come from CSV text lines (the service opens the file):
a header naming three columns (``vx,vy,vz`` for volts or ``cx,cy,cz`` for counts, or give ``columns``), then one
row per sample.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any

import numpy as np

from magnet.drivers.base import Reading
from magnet.frames import orientation_matrix

VOLT_COLUMNS = ("vx", "vy", "vz")
COUNT_COLUMNS = ("cx", "cy", "cz")


@dataclasses.dataclass(frozen=True)
class BridgeSettings:
    """Analog chain: bridge supply (V), sensitivity (mV/V/gauss), amplifier gain, and for counts the ADC."""

    supply_v: float = 3.0
    sensitivity_mv_per_v_per_gauss: float = 1.0
    amplifier_gain: float = 1.0
    adc_bits: int = 16
    vref_v: float = 3.3
    zero_counts: float = 0.0

    def __post_init__(self) -> None:
        if self.supply_v <= 0 or self.sensitivity_mv_per_v_per_gauss <= 0 or self.amplifier_gain == 0:
            raise ValueError("HMC1043 supply, sensitivity and amplifier gain must be non-zero (supply > 0)")

    @property
    def volts_per_ut(self) -> float:
        return self.amplifier_gain * self.supply_v * self.sensitivity_mv_per_v_per_gauss / 1000.0 / 100.0

    def counts_to_volts(self, counts: np.ndarray) -> np.ndarray:
        return (counts - self.zero_counts) * self.vref_v / 2**self.adc_bits


class HMC1043:
    """Replay source: ``read()`` returns the next sample as a ``Reading`` (``ready=False`` once exhausted)."""

    def __init__(
        self, samples: Any, *, unit: str = "volts", settings: BridgeSettings | None = None, orientation: Any = None
    ) -> None:
        if unit not in ("volts", "counts"):
            raise ValueError(f"HMC1043 replay unit must be 'volts' or 'counts', got {unit!r}")
        values = np.asarray(samples, dtype=float)
        if values.ndim != 2 or values.shape[1] != 3:
            raise ValueError(f"HMC1043 replay needs rows of 3 values, got shape {values.shape}")
        self.settings = settings or BridgeSettings()
        volts = self.settings.counts_to_volts(values) if unit == "counts" else values
        self.field_ut = volts / self.settings.volts_per_ut @ orientation_matrix(orientation).T
        self.index = 0

    @classmethod
    def from_csv(
        cls,
        lines: Iterable[str],
        *,
        columns: tuple[str, str, str] | None = None,
        settings: BridgeSettings | None = None,
        orientation: Any = None,
    ) -> HMC1043:
        """Parse CSV text lines: a header, then numbers. Volts or counts are told by the column names."""
        rows = [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]
        if not rows:
            raise ValueError("HMC1043 replay: the CSV is empty")
        header = [name.strip().lower() for name in rows[0].split(",")]
        wanted = columns or (VOLT_COLUMNS if set(VOLT_COLUMNS) <= set(header) else COUNT_COLUMNS)
        missing = [name for name in wanted if name not in header]
        if missing:
            raise ValueError(
                f"HMC1043 replay: the CSV header lacks {missing}; give vx,vy,vz (volts) or cx,cy,cz (ADC counts)"
            )
        index = [header.index(name) for name in wanted]
        try:
            data = [[float(row.split(",")[i]) for i in index] for row in rows[1:]]
        except (ValueError, IndexError) as exc:
            raise ValueError(f"HMC1043 replay: a row is not numeric or too short ({exc})") from None
        unit = "counts" if tuple(wanted) == COUNT_COLUMNS else "volts"
        return cls(np.array(data).reshape(-1, 3), unit=unit, settings=settings, orientation=orientation)

    def __len__(self) -> int:
        return len(self.field_ut)

    def read(self) -> Reading:
        if self.index >= len(self.field_ut):
            return Reading(ready=False)
        field = self.field_ut[self.index]
        self.index += 1
        return Reading(mag_ut=field.copy())
