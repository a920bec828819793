"""Lab programs in the style of the seed papers: training and held-out validation runs.

Training (one drawn per case): the RLG dynamic test (soak hot, power on, cool at about 1 C/min to
the cold end, soak, heat back), the patent's rate cycle (-20..+50 C at +-0.5/1/2 C/min) and a
staircase of soaks joined by 2 C/min ramps.  Validation: another start, rate and end inside the
trained range, or colder / hotter / steeper than training (the product scores only the in-range
part).  Every run starts with the gyro off for a few minutes (the logger runs first).
"""
from __future__ import annotations

from tests.referee4.physics import Program


def _u(rng, a, b):
    return float(rng.uniform(a, b))


def train_dynamic(rng, power_cycle: bool) -> Program:
    hot, cold = _u(rng, 40, 50), _u(rng, -35, -25)
    p = Program.start(hot).soak(_u(rng, 40, 70))
    p.ramp(cold, _u(rng, 0.6, 1.3)).soak(_u(rng, 30, 60))
    mid = p.end
    p.ramp(hot, _u(rng, 0.5, 1.2)).soak(_u(rng, 20, 40))
    return _power(rng, p, power_cycle, mid)


def train_cycle(rng, power_cycle: bool) -> Program:
    lo, hi = _u(rng, -22, -18), _u(rng, 48, 52)
    p = Program.start(_u(rng, 18, 25)).soak(_u(rng, 30, 50))
    p.ramp(hi, 1.0).soak(_u(rng, 15, 30))
    p.ramp(lo, 2.0).soak(_u(rng, 15, 30))
    mid = p.end
    p.ramp(hi, 0.5).soak(_u(rng, 15, 25))
    p.ramp(_u(rng, 15, 25), 1.0).soak(_u(rng, 10, 20))
    return _power(rng, p, power_cycle, mid)


def train_staircase(rng, power_cycle: bool) -> Program:
    start, step = _u(rng, -32, -26), _u(rng, 12, 16)
    p = Program.start(start).soak(_u(rng, 40, 60))
    temp = start
    mid = None
    for i in range(5):
        temp += step
        p.ramp(temp, 2.0).soak(_u(rng, 35, 50))
        if i == 2:
            mid = p.end
    p.ramp(_u(rng, -5, 5), _u(rng, 0.8, 1.2)).soak(_u(rng, 20, 30))
    return _power(rng, p, power_cycle, mid)


TRAIN = {"dynamic": train_dynamic, "cycle": train_cycle, "staircase": train_staircase}


def validate_program(rng, style: str, train: Program) -> Program:
    """``inside``: within the trained temperatures at trained rates; ``colder`` / ``hotter``: past
    one end; ``steeper``: ramps faster than any in training."""
    lo, hi = min(train.temps), max(train.temps)
    span = hi - lo
    if style == "inside":
        a, b = lo + _u(rng, 0.15, 0.3) * span, hi - _u(rng, 0.1, 0.25) * span
        p = Program.start(b).soak(_u(rng, 20, 40))
        p.ramp(a, _u(rng, 0.5, 1.0)).soak(_u(rng, 20, 40))
        p.ramp(b - _u(rng, 0, 0.1) * span, _u(rng, 0.6, 1.1)).soak(_u(rng, 15, 30))
    elif style == "colder":
        p = Program.start(hi - 0.3 * span).soak(_u(rng, 30, 50))
        p.ramp(lo - _u(rng, 4, 8), _u(rng, 0.4, 0.7)).soak(_u(rng, 30, 45))
        p.ramp(lo + 0.5 * span, _u(rng, 0.4, 0.7)).soak(_u(rng, 20, 30))
    elif style == "hotter":
        p = Program.start(lo + 0.4 * span).soak(_u(rng, 30, 50))
        p.ramp(hi + _u(rng, 4, 8), _u(rng, 0.4, 0.7)).soak(_u(rng, 30, 45))
        p.ramp(lo + 0.4 * span, _u(rng, 0.4, 0.7)).soak(_u(rng, 20, 30))
    elif style == "steeper":
        p = Program.start(hi - 0.1 * span).soak(_u(rng, 20, 40))
        p.ramp(lo + 0.15 * span, _u(rng, 2.5, 3.0)).soak(_u(rng, 40, 60))
        p.ramp(hi - 0.2 * span, _u(rng, 0.6, 1.0)).soak(_u(rng, 20, 30))
    else:
        raise ValueError(f"unknown validation style {style!r}")
    p.power_on_at(_u(rng, 300, 900))
    return p


def _power(rng, p: Program, power_cycle: bool, mid: float) -> Program:
    on = _u(rng, 300, 900)
    if power_cycle:
        off = mid + _u(rng, -600, 600)
        p.power_on_at(on, off)
        p.power_on_at(off + _u(rng, 1200, 2400))
    else:
        p.power_on_at(on)
    return p


def draw_train(rng, *, power_cycle: bool) -> tuple[str, Program]:
    style = str(rng.choice(sorted(TRAIN)))
    return style, TRAIN[style](rng, power_cycle)


def draw_validate_style(rng) -> str:
    return str(rng.choice(["inside", "inside", "colder", "hotter", "steeper"]))

