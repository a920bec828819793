"""A simulated bench with several gyros in one chamber (``MultiGyroBench``).

One chamber, one turntable and one multi-channel SCPI supply (``MultiChannelPsuSimulator``, channel
k powers the k-th slot on it) as on ``SimulatedBench``; the slots named in ``own_supplies`` are each
powered by a supply of their own instead (a ``PsuSimulator`` on its own endpoint); per slot a gyro on its own serial endpoint, its own
DS18B20 tree (its own directory and serials) and its own physics, coupled to the shared chamber air
and table and to its own supply channel.  Slots are ``g1``, ``g2``... in order.

Unit-to-unit variation (``unit_scenario``): each unit's scenario is the given one with every bias
intercept shifted and every bias coefficient, ARW and Gauss-Markov sigma scaled by seeded normal
draws (``spread``), and its own noise seed; the draws depend only on (scenario seed, unit index),
so a unit's data are the same whatever the number of units beside it.  ``unit_effects`` gives some
units an extra (hidden) effect: ``{"g2": {"warmup": {...}}}`` merges into that unit's ``effects``.

Lockstep: every unit serves under ``gyro:<slot>`` / ``w1:<slot>`` (every gyro before any probe tree,
as on ``SimulatedBench``); each driver's gyro link receives under its slot's name.

``drop_line(slot, t_from, t_to=None)``: that unit's line drops at bench time ``t_from`` (the
simulator closes the connection and stops listening, as ``GyroFaults.drop_link``), and comes back at
``t_to`` (None: for the rest of the session); both happen while the clock serves those instants, so
the fault lands on the same bench instant at any speed and load.

``drop_supply(slot, t_from, t_to=None)``: the own supply of that slot becomes unreachable at bench
time ``t_from`` (its connections closed, its port refusing) and listens again at ``t_to``; the
supply itself (its output, its settings) is unchanged meanwhile, as a supply behind a broken
serial-to-TCP bridge.  ``drop_supply(None, ...)`` does the same to the bench's multi-channel supply
(every slot on its channels at once).  Lockstep only, like ``drop_line``.
"""
from __future__ import annotations

import contextlib
import math
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.config import BenchConfig, GyroConfig, GyroSlot, ProbeConfig, PsuConfig, SlotPower
from bench.devices.orientation import check_geometry
from bench.sim.bench import SimulatedBench, _BenchInputs, _load_scenario, _RowInputs, device_inputs_row
from bench.sim.gyro import GyroStreamSimulator
from bench.sim.lookahead import Lookahead
from bench.sim.physics import GyroPhysics
from bench.sim.psu import MultiChannelPsuSimulator, PsuModel, PsuSimulator
from bench.sim.scenario import Scenario
from bench.sim.w1 import W1TreeSimulator

# default unit-to-unit spread: intercepts (deg/h, absolute), coefficients and noise (relative)
DEFAULT_SPREAD = {"intercept_dph": 0.5, "coefficient_rel": 0.2, "noise_rel": 0.15}


def simulated_bench(units: int | None = None, **kwargs: Any) -> SimulatedBench:
    """The simulated bench of a command: one gyro (``units`` None), or ``units`` gyros in one chamber."""
    return MultiGyroBench(units=units, **kwargs) if units else SimulatedBench(**kwargs)


def slot_name(index: int) -> str:
    return f"g{index + 1}"


def unit_scenario(base: Scenario, index: int, spread: dict[str, float] | None = None,
                  effects: dict[str, Any] | None = None) -> Scenario:
    """Unit ``index``'s scenario: ``base`` varied by seeded draws (see the module docstring)."""
    sp = {**DEFAULT_SPREAD, **(spread or {})}
    rng = np.random.default_rng([int(base.seed), 7919, int(index)])
    data = base.model_dump()
    for bias in data["bias"].values():
        bias["intercept_dph"] = bias["intercept_dph"] + sp["intercept_dph"] * float(rng.standard_normal())
        bias["terms"] = {term: coef * (1.0 + sp["coefficient_rel"] * float(rng.standard_normal()))
                         for term, coef in bias["terms"].items()}
    for noise in data["noise"].values():
        scale = max(0.1, 1.0 + sp["noise_rel"] * float(rng.standard_normal()))
        noise["arw_deg_rt_h"] *= scale
        for gm in noise["gauss_markov"]:
            gm["sigma_dph"] *= scale
    data["seed"] = int(base.seed) * 1000 + int(index) + 1
    data["name"] = f"{base.name}/{slot_name(index)}"
    if effects:
        unknown = set(effects) - set(data["effects"])
        if unknown:
            raise ValueError(f"unit {slot_name(index)}: unknown effect(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(data['effects']))})")
        data["effects"] = {**data["effects"], **effects}
    return Scenario.from_dict(data, source=f"{base.name} unit {slot_name(index)}")


class _UnitView:
    """What ``_BenchInputs`` needs from a bench, for one unit: the shared chamber and table, the
    unit's own supply channel and mounting."""

    _air_c = SimulatedBench._air_c
    _angles = SimulatedBench._angles
    _body_to_level = SimulatedBench._body_to_level
    _table_rate_body = SimulatedBench._table_rate_body
    _powered = SimulatedBench._powered
    _power_on_time = SimulatedBench._power_on_time

    def __init__(self, bench: SimulatedBench, psu_model: PsuModel, mounting: str) -> None:
        self.clock = bench.clock
        self.geometry = bench.geometry.model_copy(update={"mounting": mounting})
        self._outer_axis, self._inner_axis, self._mounting = check_geometry(self.geometry)
        self.chamber_model = bench.chamber_model
        self.table_model = bench.table_model
        self.device_track = bench.device_track
        self.psu_model = psu_model


@dataclass
class SimUnit:
    slot: str
    index: int
    scenario: Scenario
    psu_model: PsuModel
    physics: GyroPhysics
    gyro: GyroStreamSimulator
    w1: W1TreeSimulator
    serials: dict[str, str]
    serve_name: str
    w1_name: str
    mounting: str
    lookahead: Lookahead | None = None        # lockstep: the physics integrated in blocks (bench.sim.lookahead)


class MultiGyroBench(SimulatedBench):
    """``SimulatedBench`` with ``units`` gyros (see the module docstring)."""

    def __init__(self, *, units: int, scenario: str | Scenario = "default", seed: int | None = None,
                 latitude_deg: float | None = None, spread: dict[str, float] | None = None,
                 unit_effects: dict[str, dict[str, Any]] | None = None,
                 mountings: dict[str, str] | None = None, own_supplies: tuple[str, ...] | list[str] = (),
                 **kwargs: Any) -> None:
        if not isinstance(units, int) or isinstance(units, bool) or not 1 <= units <= 64:
            raise ValueError(f"units must be an integer 1..64, got {units!r}")
        base = scenario if isinstance(scenario, Scenario) else _load_scenario(scenario)
        if latitude_deg is not None:
            base = base.with_changes(latitude_deg=latitude_deg)
        if seed is not None:
            base = base.with_changes(seed=int(seed))
        slots = [slot_name(k) for k in range(units)]
        own_supplies = tuple(own_supplies)
        if own_supplies and set(own_supplies) >= set(slots):
            raise ValueError("own_supplies: at least one slot stays on the bench's multi-channel supply")
        for where, given in (("unit_effects", unit_effects or {}), ("mountings", mountings or {}),
                             ("own_supplies", dict.fromkeys(own_supplies))):
            unknown = set(given) - set(slots)
            if unknown:
                raise ValueError(f"{where}: no slot {', '.join(sorted(unknown))} (slots: {', '.join(slots)})")
        scenarios = [unit_scenario(base, k, spread, (unit_effects or {}).get(s)) for k, s in enumerate(slots)]
        self.base_scenario = base
        super().__init__(scenario=scenarios[0], **kwargs)
        self.seed = base.seed
        mountings = mountings or {}
        bench_mounting = self.geometry.mounting
        first_mounting = mountings.get(slots[0], bench_mounting)
        if first_mounting != self.geometry.mounting:
            self.geometry = self.geometry.model_copy(update={"mounting": first_mounting})
            self._outer_axis, self._inner_axis, self._mounting = check_geometry(self.geometry)
        self.units: list[SimUnit] = [SimUnit(slots[0], 0, scenarios[0], self.psu_model, self.physics, self.gyro,
                                             self.w1, dict(self.serials), f"gyro:{slots[0]}", f"w1:{slots[0]}",
                                             first_mounting, self.lookahead)]
        t0 = self.clock.now()
        frame = "hrg" if base.gyro_type == "hrg" else "kvh_a"
        for k in range(1, units):
            psu_model = PsuModel()
            psu_model.advance_to(t0)
            mounting = mountings.get(slots[k], bench_mounting)
            view = _UnitView(self, psu_model, mounting)
            lookahead = None
            if self.lockstep:      # as SimulatedBench: exact device states, blocks ahead of the clock
                inputs = _RowInputs(view)  # type: ignore[arg-type]
                inputs.rows[t0] = device_inputs_row(view, view.chamber_model, view.table_model, psu_model, t0)  # type: ignore[arg-type]
                physics = GyroPhysics(scenarios[k], t0, inputs, output_period_s=1.0 / self.data_rate_hz)
                lookahead = Lookahead(view, physics, inputs)  # type: ignore[arg-type]
            else:
                physics = GyroPhysics(scenarios[k], t0, _BenchInputs(view),  # type: ignore[arg-type]
                                      output_period_s=1.0 / self.data_rate_hz)
            source = lookahead or physics
            serials = {name: f"{k:04x}{0xA1B2C300 + i:08x}" for i, name in enumerate(self.probe_names)}
            root = Path(tempfile.mkdtemp(prefix=f"bench-w1-{slots[k]}-", dir=self.w1_root.parent))
            self.units.append(SimUnit(
                slots[k], k, scenarios[k], psu_model, physics,
                GyroStreamSimulator(source, self.clock, self.data_rate_hz, frame, seed=12345 + k),
                W1TreeSimulator(source, self.clock, root, serials, min_wall_interval_s=0.005),
                serials, f"gyro:{slots[k]}", f"w1:{slots[k]}", mounting, lookahead))
        on_channels = [u for u in self.units if u.slot not in own_supplies]
        self.psu = MultiChannelPsuSimulator([u.psu_model for u in on_channels], self.clock)
        self.psu_channels = {u.slot: k + 1 for k, u in enumerate(on_channels)}
        self.own_psus = {u.slot: PsuSimulator(u.psu_model, self.clock) for u in self.units if u.slot in own_supplies}
        self._drops: dict[str, list[float | None]] = {}
        self._supply_drops: dict[str | None, list[float | None]] = {}     # slot (None: the bench's supply)

    # ---------------------------------------------------------------- faults by bench time
    def drop_line(self, slot: str, t_from: float, t_to: float | None = None) -> None:
        unit = self.unit(slot)
        if t_to is not None and t_to <= t_from:
            raise ValueError(f"drop_line {slot}: t_to {t_to} is not after t_from {t_from}")
        self._drops[unit.slot] = [float(t_from), None if t_to is None else float(t_to)]

    def drop_supply(self, slot: str | None, t_from: float, t_to: float | None = None) -> None:
        """``slot``'s own supply (None: the bench's multi-channel supply) unreachable from ``t_from`` to ``t_to``."""
        if slot is not None:
            unit = self.unit(slot)
            if unit.slot not in self.own_psus:
                raise ValueError(f"drop_supply {slot}: the slot is powered by channel {self.psu_channels[unit.slot]} of "
                                 f"the bench's supply, not by a supply of its own (own_supplies); "
                                 f"drop_supply(None, ...) drops the bench's supply")
            slot = unit.slot
        what = slot or "(the bench's supply)"
        if not self.lockstep:
            raise ValueError(f"drop_supply {what}: faults by bench time need the lockstep clock")
        if t_to is not None and t_to <= t_from:
            raise ValueError(f"drop_supply {what}: t_to {t_to} is not after t_from {t_from}")
        self._supply_drops[slot] = [float(t_from), None if t_to is None else float(t_to)]

    def _serve_supplies(self, t: float) -> dict:
        """Lockstep: the supply drops due at bench time ``t`` (``drop_supply``), at that instant."""
        for slot, drop in list(self._supply_drops.items()):
            supply = self.psu if slot is None else self.own_psus[slot]
            t_from, t_to = drop
            if not math.isnan(t_from) and t >= t_from:
                supply.faults.drop_link(refuse_s=math.inf)
                drop[0] = math.nan
            if t_to is not None and math.isnan(drop[0]) and t >= t_to:
                supply.faults.restore_link()
                del self._supply_drops[slot]
        return {}

    def unit(self, slot: str) -> SimUnit:
        for unit in self.units:
            if unit.slot == slot:
                return unit
        raise KeyError(f"no simulated gyro slot {slot!r} (slots: {', '.join(u.slot for u in self.units)})")

    def _serve_gyro(self, unit: SimUnit):
        def serve(t: float) -> dict:
            drop = self._drops.get(unit.slot)
            if drop is not None:
                t_from, t_to = drop
                if not math.isnan(t_from) and t >= t_from:
                    unit.gyro.faults.drop_link(None)   # serve() acts on it at this instant
                    drop[0] = math.nan
                if t_to is not None and math.isnan(drop[0]) and t >= t_to:
                    unit.gyro.faults.restore_link()
                    del self._drops[unit.slot]
            return unit.gyro.serve(t)
        return serve

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> "MultiGyroBench":
        if self.started:
            return self
        self.chamber.start()
        for server in (self.turntable, self.psu, *self.own_psus.values()):
            server.start()
        for unit in self.units:
            unit.gyro.start()
            unit.w1.start()
        if self.lockstep:
            for unit in self.units:          # every gyro first (see SimulatedBench.start), then the probes
                self.clock.serve(unit.serve_name, self._serve_gyro(unit))
            for unit in self.units:
                self.clock.serve(unit.w1_name, unit.w1.serve)
            self.clock.serve("psu:faults", self._serve_supplies)
        self.started = True
        return self

    def stop(self) -> None:
        if self.lockstep:
            self.clock.forget("psu:faults")
            for unit in self.units:
                self.clock.forget(unit.w1_name)
                self.clock.forget(unit.serve_name)
        for supply in self.own_psus.values():
            try:
                supply.stop()
            except Exception:   # noqa: BLE001 - stopping must reach every server
                pass
        for unit in self.units[1:]:
            for server in (unit.w1, unit.gyro):
                try:
                    server.stop()
                except Exception:   # noqa: BLE001 - stopping must reach every server
                    pass
            shutil.rmtree(unit.w1.root, ignore_errors=True)      # made by this bench (next to the first tree)
        super().stop()

    def snapshot(self) -> dict[str, Any]:
        with self._lock, contextlib.ExitStack() as at_instant:
            for unit in self.units[1:]:
                if unit.lookahead is not None:   # each unit's physics at the instant, its block kept
                    at_instant.enter_context(unit.lookahead.at_instant())
            return super().snapshot()

    def restore(self, snap: dict[str, Any]) -> float:
        t = super().restore(snap)
        with self._lock:
            for unit in self.units[1:]:
                if unit.lookahead is not None:
                    unit.lookahead.reset(t)
        return t

    def _state_objects(self) -> dict[str, Any]:
        objs = super()._state_objects()
        for unit in self.units[1:]:
            objs.update({f"psu:{unit.slot}": unit.psu_model, f"physics:{unit.slot}": unit.physics,
                         f"w1:{unit.slot}": unit.w1, f"gyro:{unit.slot}": unit.gyro})
            if unit.lookahead is None:
                objs[f"inputs:{unit.slot}"] = unit.physics.inputs
        return objs

    # ---------------------------------------------------------------- addresses
    @property
    def endpoints(self) -> dict[str, Any]:
        doc = super().endpoints
        doc["units"] = {u.slot: {"gyro": u.gyro.url, "w1_root": str(u.w1.root), "probes": dict(u.serials),
                                 "psu_channel": self.psu_channels.get(u.slot),
                                 "psu": self.own_psus[u.slot].url if u.slot in self.own_psus else None,
                                 "scenario": u.scenario.name, "seed": u.scenario.seed,
                                 "mounting": u.mounting}
                        for u in self.units}
        return doc

    def bench_config(self, *, chamber_transport: str = "modbus_tcp") -> BenchConfig:
        single = super().bench_config(chamber_transport=chamber_transport)
        slots = []
        for u in self.units:
            gyro = single.gyro.model_copy(update={"url": u.gyro.url,
                                                  "channel_probes": u.scenario.channel_probe_map()})
            slots.append(GyroSlot(slot=u.slot, gyro=GyroConfig.model_validate(gyro.model_dump()),
                                  probes=ProbeConfig(w1_root=str(u.w1.root), probes=dict(u.serials)),
                                  power=self._slot_power(u, single.psu), mounting=u.mounting))
        return BenchConfig.model_validate({**single.model_dump(), "gyros": [s.model_dump() for s in slots]})

    def _slot_power(self, unit: SimUnit, bench_psu: PsuConfig) -> SlotPower:
        own = self.own_psus.get(unit.slot)
        if own is None:
            return SlotPower(channel=self.psu_channels[unit.slot])
        return SlotPower(psu=bench_psu.model_copy(update={"url": own.url}))

    def truth(self) -> dict[str, Any]:
        """Each unit's true coefficients (``Scenario.truth``), by slot."""
        return {u.slot: u.scenario.truth() for u in self.units}
