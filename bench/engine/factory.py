"""Wiring the engine to a bench: real drivers from a ``BenchConfig``, engine timing for an accelerated
clock, and the fit hook that fits a procedure's declared models on the stored run.

``build_devices(config, clock)`` opens nothing by itself (drivers connect on first use, the gyro link
on ``Engine`` start); ``close_devices`` closes every driver and never raises.

``engine_config_for(clock)``: engine timing in bench seconds.  Real hardware (``RealClock``) and the
stepped test clock keep the defaults: probes every 2 s, chamber status every 5 s, turntable and PSU
every 10 s, a 1 s fine tick and 10 s soak tick.  The simulated bench runs on a ``LockstepClock``, where bench
time only moves when the engine sleeps and every sample is served before it does, so the same rates
hold at any speed; its loop ticks every 2 s (the probe period) in soaks too.  An ``AcceleratedClock``
(a free-running simulated bench, as some tests start beside a worker) keeps the defaults as well: its
samples are late when the host is slow, which the run's ``sampling`` summary shows.  (``bench sim up``
in another process is in lockstep too: the engine's process drives its clock, ``bench.clocklink``.)

``writer_options_for(clock)``: the frame writers' settings (``bench.storage.FrameWriter``).  Each run's writer
commits every half wall second by default; on a lockstep clock running faster than the wall (``--speed max``
or a pace above x1) that is minutes of bench time either way, and with a writer per gyro unit (nine on an
eight-gyro run, each commit a synchronised write of the database journal) the commits cost more than the
rows: they commit every ``LOCKSTEP_FLUSH_S`` wall seconds there.  The data do not change (the same frames
and rows, in fewer transactions); a crash loses at most that much more of the run's tail, which the resume
records as a gap as before.

``make_fit_hook(db, store, latitude_deg=)``: the engine's ``Fit`` step calls it.  It flushes the
run's writer, builds the run's measured-data ``Dataset`` (``bench.storage.export.run_dataset``: 1-s
means of the recorded segments), keeps the rows of the segments named by the step's
``options["train"]`` label filter (e.g. ``{"set": "model"}``), fits every model of the step on every
gyro channel through ``bench.fit.catalog.fit_model`` (per-model options from
``options["model_options"][model]``), and stores the ``FitResult``s as the next version of each model
for the run's gyro in the ``fits`` table (``queries.save_fits``, accepted).  A model that cannot be
fitted on a channel is reported in the result's ``errors``; if nothing could be fitted the step
fails (the run itself is kept).
"""
from __future__ import annotations

import threading
from typing import Any

from bench.clock import Clock
from bench.config import BenchConfig
from bench.engine.config import EngineConfig
from bench.engine.devices import Devices, UnitDevices
from bench.engine.steps import Fit
from bench.errors import BenchError



def build_devices(config: BenchConfig, clock: Clock) -> Devices:
    """The real drivers for ``config`` (the same ones talk to the simulators).  A multi-gyro bench
    (``config.gyros``) gives a fixture: per slot its gyro link (lockstep name ``gyro:<slot>``), its
    probes and its power, a channel of the one ``config.psu`` supply or a supply of its own."""
    from bench.devices.chamber import WatlowF4Chamber
    from bench.devices.ds18b20 import W1ProbeArray
    from bench.devices.gyro import GyroSerialLink
    from bench.devices.psu import PsuChannel, ScpiPowerSupply
    from bench.devices.turntable import AcutrolTurntable

    chamber = WatlowF4Chamber(config.chamber, clock)
    turntable = AcutrolTurntable(config.turntable, clock)
    if not config.multi:
        return Devices(chamber=chamber, turntable=turntable, gyro=GyroSerialLink(config.gyro, clock),
                       probes=W1ProbeArray(config.probes), psu=ScpiPowerSupply(config.psu))
    shared = ScpiPowerSupply(config.psu) if any(s.power.channel is not None for s in config.gyros) else None
    lock = shared.channel_lock if shared is not None else threading.Lock()
    units = []
    for slot in config.gyros:
        own = slot.power.psu
        psu = ScpiPowerSupply(own) if own is not None else PsuChannel(shared, slot.power.channel, lock)
        supply_cfg = own or config.psu
        units.append(UnitDevices(
            slot=slot.slot, gyro=GyroSerialLink(slot.gyro, clock, lockstep_name=f"gyro:{slot.slot}"),
            probes=W1ProbeArray(slot.probes), psu=psu,
            voltage_v=slot.power.voltage_v if slot.power.voltage_v is not None else supply_cfg.voltage_v,
            current_limit_a=(slot.power.current_limit_a if slot.power.current_limit_a is not None
                             else supply_cfg.current_limit_a),
            shared_power=own is None))
    return Devices.fixture(chamber, turntable, units, shared=[shared] if shared is not None else [])


def close_devices(devices: Devices) -> list[str]:
    """Close every driver; returns the problems met (closing must reach every device)."""
    problems: list[str] = []
    closers = [("gyro link", devices.gyro.stop), ("chamber", devices.chamber.close),
               ("turntable", devices.turntable.close), ("power supply", devices.psu.close)]
    closers += [("shared power supply", supply.close) for supply in devices.shared]
    for name, action in closers:
        try:
            action()
        except Exception as exc:  # noqa: BLE001 - report and go on
            problems.append(f"{name}: {type(exc).__name__}: {exc}")
    return problems


LOCKSTEP_FLUSH_S = 2.0


def writer_options_for(clock: Clock) -> dict[str, Any]:
    """``SqlRunStore(writer_options=...)`` for ``clock`` (see the module docstring)."""
    if getattr(clock, "lockstep", False):
        pace = getattr(clock, "pace", None)
        if pace is None or pace > 1.0:
            return {"flush_interval_s": LOCKSTEP_FLUSH_S}
    return {}


def engine_config_for(clock: Clock, base: EngineConfig | None = None) -> EngineConfig:
    """Engine timing for ``clock`` (see the module docstring)."""
    cfg = base or EngineConfig()
    if getattr(clock, "lockstep", False):
        return cfg.model_copy(update={"max_tick_s": min(cfg.max_tick_s, cfg.probe_period_s),
                                      "tick_s": min(cfg.max_tick_s, cfg.probe_period_s)})
    return cfg


# ---- fitting --------------------------------------------------------------------------------------
def make_fit_hook(db, store, *, latitude_deg: float | None, accept: bool = True):
    """Engine ``FitHook`` storing the fitted models in the ``fits`` table (see the module docstring)."""

    def hook(run_id: str, index: int, step: Fit, _store: Any) -> dict[str, Any]:
        from bench.storage import queries

        rid = int(run_id)
        with db.session() as s:
            units = [(u.slot, int(u.id)) for u in queries.unit_runs(s, rid)]
        if not units:
            return fit_run(rid, step)
        # a multi-gyro run: the procedure's fits on each gyro's own run, stored under its gyro id
        results: dict[str, Any] = {}
        for slot, unit_rid in units:
            try:
                results[slot] = {"run_id": unit_rid, **fit_run(unit_rid, step)}
            except BenchError as exc:
                results[slot] = {"run_id": unit_rid, "status": "failed", "error": str(exc)}
        if not any(r.get("status") == "done" for r in results.values()):
            raise BenchError(f"run {rid}: no gyro could be fitted: "
                             + "; ".join(f"{slot}: {r.get('error') or r.get('reason')}" for slot, r in results.items()))
        return {"status": "done", "units": results}

    def fit_run(rid: int, step: Fit) -> dict[str, Any]:
        from bench.fit.catalog import fit_model
        from bench.storage import queries
        from bench.storage.export import run_dataset

        store.flush(rid)
        with db.session() as s:
            gyro_id = queries.get_run(s, rid).gyro_id
        if gyro_id is None:
            return {"status": "skipped", "reason": "run has no gyro id", "models": list(step.models)}
        train = step.options.get("train") if isinstance(step.options.get("train"), dict) else None
        ds = run_dataset(rid, db, latitude_deg=latitude_deg, where=train)
        if len(ds) < 10:
            raise BenchError(f"run {rid}: only {len(ds)} recorded seconds"
                             f"{' in ' + repr(train) if train else ''}; too few to fit {', '.join(step.models)}")
        model_options = step.options.get("model_options") or {}
        results, errors = [], {}
        for model in step.models:
            for channel in ds.gyro_channels():
                try:
                    results.append(fit_model(model, ds, channel, **dict(model_options.get(model) or {})))
                except (BenchError, ValueError, KeyError, ArithmeticError, TypeError) as exc:
                    errors[f"{model}/{channel}"] = f"{type(exc).__name__}: {exc}"
        if not results:
            raise BenchError(f"run {rid}: no model could be fitted: {errors}")
        with db.session() as s:
            versions = queries.save_fits(s, gyro_id, [rid], results, accepted=accept)
        return {"status": "done", "gyro_id": gyro_id, "versions": versions, "accepted": accept,
                "rows": len(ds), "train": train,
                "fitted": sorted(f"{r.model}/{r.channel}" for r in results),
                "rms_dph": {f"{r.model}/{r.channel}": r.stats.get("rms_dph") for r in results},
                "errors": errors}

    return hook
