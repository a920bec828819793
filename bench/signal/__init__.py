"""The signal vocabulary: the one definition of each operation the fitting, close-the-loop, simulator
and engine code share.  Pure functions over numpy arrays; units in every docstring.

* ``segments``: ``run_segments``, ``block_means`` (segment-aware, NaN ignored per column), ``BlockPlan``
  (the same blocks computed once for many columns).
* ``rate``: ``temperature_rate(time_s, temp_c, window_s, method=...)`` in C/min
  (``RATE_METHODS``: "centred_slope", "savgol2"), ``smoothed_temperature``; ``CentredSlopeRate`` for
  one record's centred-slope rate at many windows.
* ``glitches``: ``isolated_glitches(time_s, x, min_deviation, labels)`` (a Hampel filter along the
  robust local line, with a motion allowance: corrupted frames, a probe's power-on reading).
* ``allan``: ``allan_deviation`` (one NaN policy, ``MIN_ALLAN_SAMPLES``).
* ``stats``: ``lag1_autocorrelation``, ``newey_west_lags``, ``ols_hac`` -> ``HacFit``, ``hac_wald_test``
  (chi2), ``ljung_box``.
* ``recurrence``: ``linear_recurrence`` (y[i] = a[i] y[i-1] + b[i], vectorised: lags on irregular time
  axes, hysteresis memories).
* ``lstsq``: ``lstsq`` (column-equilibrated, rows with a non-finite value dropped) -> ``LinearFit``.
* ``geometry``: orientation codes, ``EARTH_RATE_DPH``, ``earth_rate_enu`` / ``earth_rate_body``.
"""
from bench.signal.allan import MIN_ALLAN_SAMPLES, AllanDeviation, allan_deviation
from bench.signal.glitches import isolated_glitches
from bench.signal.geometry import (
    DEFAULT_ORIENTATION,
    EARTH_RATE_DPH,
    EIGHT_POSITIONS,
    OrientationError,
    code_matrix,
    earth_rate_body,
    earth_rate_body_per_sample,
    earth_rate_enu,
    orientation_axes,
    orientation_axes_per_sample,
    validate_canonical_code,
    validate_code,
)
from bench.signal.lstsq import LinearFit, bic, lstsq
from bench.signal.rate import (
    DEFAULT_RATE_METHOD,
    CentredSlopeRate,
    RATE_METHODS,
    check_rate_method,
    smoothed_temperature,
    smoothed_temperature_and_rate,
    temperature_rate,
)
from bench.signal.recurrence import linear_recurrence
from bench.signal.segments import BlockMeans, BlockPlan, block_means, run_segments
from bench.signal.stats import (
    HacFit,
    WaldTest,
    column_scale,
    finite_rows,
    hac_wald_test,
    lag1_autocorrelation,
    ljung_box,
    newey_west_lags,
    ols_hac,
)

__all__ = [
    "AllanDeviation", "BlockMeans", "BlockPlan", "CentredSlopeRate", "DEFAULT_ORIENTATION", "DEFAULT_RATE_METHOD", "EARTH_RATE_DPH",
    "EIGHT_POSITIONS", "HacFit", "LinearFit", "MIN_ALLAN_SAMPLES", "OrientationError", "RATE_METHODS", "WaldTest",
    "allan_deviation", "bic", "block_means", "check_rate_method", "code_matrix", "column_scale",
    "earth_rate_body", "earth_rate_body_per_sample", "earth_rate_enu", "finite_rows", "hac_wald_test", "isolated_glitches",
    "lag1_autocorrelation", "linear_recurrence", "ljung_box", "lstsq", "newey_west_lags", "ols_hac", "orientation_axes",
    "orientation_axes_per_sample", "run_segments", "smoothed_temperature", "smoothed_temperature_and_rate",
    "temperature_rate", "validate_canonical_code", "validate_code",
]
