"""Run engine: plans of steps executed on the bench devices, with checkpoints, resume, control,
suspension and safe state.  See ``engine.py`` for the loop and ``steps.py`` for the step kinds."""
from bench.engine.config import EngineConfig
from bench.engine.control import COMMANDS, Control, NoControl, QueueControl
from bench.engine.devices import Devices
from bench.engine.context import HardwareState, StepContext
from bench.engine.engine import Engine, FitHook
from bench.engine.executors import StepFailed
from bench.engine.memstore import MemoryRunStore
from bench.engine.orientation import check_orientation, orientation_problem
from bench.engine.planning import (part_correlation, plan_summary, setpoint_limits, setpoint_profile,
                                   validate_plan)
from bench.engine.steps import (Fit, GyroPower, Orient, Plan, Ramp, Record, SetChamber, Soak, Step,
                                TableRate, WaitStable, WeakCorrelation)
from bench.engine.store import PsuReading, RunStore

__all__ = [
    "COMMANDS", "Control", "Devices", "Engine", "EngineConfig", "Fit", "FitHook", "GyroPower",
    "HardwareState", "MemoryRunStore", "NoControl", "Orient", "Plan", "PsuReading", "QueueControl", "Ramp", "Record",
    "RunStore", "SetChamber", "Soak", "Step", "StepContext", "StepFailed", "TableRate", "WaitStable", "WeakCorrelation",
    "check_orientation", "orientation_problem", "part_correlation", "plan_summary", "setpoint_limits",
    "setpoint_profile", "validate_plan",
]
