"""A *dataset*: named 1-D float arrays of equal length (``time_s`` in s, ``gyro_x`` in deg/h,
``temp_t1`` in C, ``freq_x`` in Hz, ``orientation`` (array of str), ...) plus metadata from the CSV
header.  The exchange type between the simulator, storage export and the fitting module; pure data.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Dataset:
    columns: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["time_s"]) if "time_s" in self.columns else 0

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.columns[name]
        except KeyError:
            raise KeyError(f"column {name!r} not in data (have: {', '.join(sorted(self.columns))})") from None

    def __contains__(self, name: str) -> bool:
        return name in self.columns

    @property
    def time(self) -> np.ndarray:
        return self.columns["time_s"]

    def gyro_channels(self) -> list[str]:
        return [c[len("gyro_"):] for c in self.columns if c.startswith("gyro_")]

    def temp_names(self) -> list[str]:
        return [c[len("temp_"):] for c in self.columns if c.startswith("temp_")]

    def select(self, mask: np.ndarray) -> "Dataset":
        return Dataset({k: v[mask] for k, v in self.columns.items()}, dict(self.meta))

    def with_columns(self, **cols: np.ndarray) -> "Dataset":
        merged = dict(self.columns)
        merged.update(cols)
        return Dataset(merged, dict(self.meta))
