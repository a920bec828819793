"""One definition of "plain JSON" for the whole package: numpy arrays and scalars -> Python values,
tuples -> lists, non-finite floats -> None (strict JSON, and PostgreSQL JSONB refuses NaN)."""
from __future__ import annotations

import math
from typing import Any


def jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if hasattr(value, "tolist") and callable(value.tolist):     # numpy arrays and scalars
        return jsonable(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value
