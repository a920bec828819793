"""Simulated-gyro scenario: everything the gyro physics needs, loaded from a strict JSON file.

Units used throughout (also in the JSON keys):

* gyro rates and biases: deg/h (``*_dph``); the wire output of the KVH stream is deg/s (the physics
  converts); ARW in deg/sqrt(h); rate random walk in deg/h/sqrt(h);
* temperatures: C; temperature rates: C/min; times and time constants: s;
* thermal capacities J/K, conductances W/K, heat inputs W;
* scale factor: ppm and ppm/C; g-sensitivity: deg/h per g.

Bias terms use a small term language (the same spirit as the fitting module's formula language):

* ``t1``     temperature of node/probe ``t1`` minus the channel's reference ``t0_c`` (C)
* ``dt1``    its rate of change (C/min)
* ``(t1-t3)`` a gradient between two nodes/probes (C, not centred); ``d(t1-t3)`` its rate (C/min)
* ``^k``     an integer power of a factor (1..6), ``*`` a product of factors:
  ``t1^2``, ``t1*dt1``, ``(t1-t3)^2``.

Names are thermal-node names or probe names.  A probe reads the node it is glued to.  The true
reference ``t0_c`` (default 25 C, seed 000 eq 3 uses t0 = 25 C) and the intercept are per channel.

Sources for the model shapes: seed 000 eq 3-5 (RLG static/dynamic: T, gradient, dT/dt in C/min),
seed 001 (four probes, T and dT/dt products), seed 002 eq 2 (HRG resonance frequency cubic),
seed 004 (FOG start-up), calibration-notes section 3 (effects and magnitudes).
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from bench.errors import DataFormatError

SCENARIO_DIR = Path(__file__).with_name("scenarios")

# Seed 002 eq 2: f2(T) = -5.751e-7 T^3 - 2.568e-4 T^2 + 4.794e-1 T + 4.896e3 (Hz, T in C, Gx gyro).
HRG_F2_COEFFS = (-5.751e-7, -2.568e-4, 4.794e-1, 4.896e3)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------------------------
# Term language
# --------------------------------------------------------------------------------------------

_IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
_FACTOR_RE = re.compile(rf"^(?P<base>d?\((?P<a>{_IDENT})-(?P<b>{_IDENT})\)|d?{_IDENT})(?:\^(?P<pow>\d+))?$")


@dataclass(frozen=True)
class Factor:
    """One factor of a bias term.  ``kind``: temp | rate | grad | grad_rate."""

    kind: str
    a: str
    b: str | None = None
    power: int = 1


def parse_term(text: str, names: set[str]) -> tuple[Factor, ...]:
    """Parse a term like ``t1^2`` or ``(t1-t3)*dt2`` against the known node/probe ``names``.

    Raises ValueError naming the offending part.
    """
    compact = text.replace(" ", "")
    if not compact:
        raise ValueError("empty term")
    factors = []
    for part in compact.split("*"):
        m = _FACTOR_RE.match(part)
        if not m:
            raise ValueError(f"term {text!r}: cannot read factor {part!r} (use name, dname, (a-b), d(a-b), ^k)")
        power = int(m["pow"]) if m["pow"] else 1
        if not 1 <= power <= 6:
            raise ValueError(f"term {text!r}: power {power} outside 1..6")
        base = m["base"]
        if m["a"] is not None:
            for n in (m["a"], m["b"]):
                if n not in names:
                    raise ValueError(f"term {text!r}: unknown temperature {n!r} (known: {', '.join(sorted(names))})")
            kind = "grad_rate" if base.startswith("d") else "grad"
            factors.append(Factor(kind, m["a"], m["b"], power))
        elif base in names:
            factors.append(Factor("temp", base, None, power))
        elif base.startswith("d") and base[1:] in names:
            factors.append(Factor("rate", base[1:], None, power))
        else:
            raise ValueError(f"term {text!r}: unknown temperature {base!r} (known: {', '.join(sorted(names))})")
    return tuple(factors)


# --------------------------------------------------------------------------------------------
# Thermal network
# --------------------------------------------------------------------------------------------


class ThermalNode(_Strict):
    capacity_j_per_k: float = Field(gt=0)
    to_air_w_per_k: float = Field(0.0, ge=0)       # convective coupling to the chamber air
    heat_w: float = Field(0.0, ge=0)               # self-heating while the gyro is powered


class ThermalLink(_Strict):
    a: str
    b: str
    w_per_k: float = Field(gt=0)


class ThermalNetwork(_Strict):
    """Lumped linear network: chamber air (boundary) -> case/mount nodes -> internal nodes.

    C_i dT_i/dt = sum_j g_ij (T_j - T_i) + g_air_i (T_air - T_i) + P_i * powered.
    """

    nodes: dict[str, ThermalNode]
    links: list[ThermalLink] = Field(default_factory=list)
    substep_s: float = Field(1.0, gt=0, le=60)
    # "equilibrium": at clock_start every node is at the steady state for the air temperature and
    # power state at that instant (a soaked gyro).
    initial: Literal["equilibrium"] = "equilibrium"

    @model_validator(mode="after")
    def _check(self) -> "ThermalNetwork":
        if not self.nodes:
            raise ValueError("thermal.nodes: at least one node is needed")
        for i, link in enumerate(self.links):
            for end in (link.a, link.b):
                if end not in self.nodes:
                    raise ValueError(f"thermal.links[{i}]: unknown node {end!r}")
            if link.a == link.b:
                raise ValueError(f"thermal.links[{i}]: a link needs two different nodes")
        # every node needs a path to the air, else its temperature is undetermined
        reached = {n for n, spec in self.nodes.items() if spec.to_air_w_per_k > 0}
        changed = True
        while changed:
            changed = False
            for link in self.links:
                if (link.a in reached) != (link.b in reached):
                    reached.update((link.a, link.b))
                    changed = True
        missing = sorted(set(self.nodes) - reached)
        if missing:
            raise ValueError(f"thermal: node(s) {', '.join(missing)} have no thermal path to the chamber air")
        return self


# --------------------------------------------------------------------------------------------
# Bias, effects, noise, HRG
# --------------------------------------------------------------------------------------------


class ChannelBias(_Strict):
    intercept_dph: float = 0.0
    t0_c: float = 25.0
    terms: dict[str, float] = Field(default_factory=dict)     # term text -> deg/h per unit of term


class ThermalLagEffect(_Strict):
    """Bias is driven by the temperatures seen through a first-order lag ``tau_s`` (all temperature
    variables of the channel's terms, their rates being the rates of the lagged signals)."""

    tau_s: float = Field(gt=0)
    channels: list[str] | None = None


class HysteresisEffect(_Strict):
    """Heating/cooling branch offset: bias += amplitude * h, with a Duhem-type state
    dh/dt = (r - |r| h) / width_c, r = d(driver)/dt.  h -> +1 after heating by a few ``width_c``,
    -1 after cooling, and keeps its value during soaks (memory)."""

    driver: str
    width_c: float = Field(gt=0)
    amplitude_dph: dict[str, float]


class WarmupEffect(_Strict):
    """bias += amplitude * exp(-(t - t_power_on) / tau_s) while powered (seed 004 start-up drift)."""

    tau_s: float = Field(gt=0)
    amplitude_dph: dict[str, float]


class GSensitivityEffect(_Strict):
    """bias_i += sum_j K_ij * f_j, f = specific force on body axes in g (+1 g along body up)."""

    dph_per_g: dict[str, tuple[float, float, float]]


class ScaleFactorEffect(_Strict):
    """output_i = (1 + 1e-6 (ppm_i + ppm_per_c_i (T_driver - t0_c))) * input_i, input incl. Earth and
    table rate."""

    ppm: dict[str, float] = Field(default_factory=dict)
    ppm_per_c: dict[str, float] = Field(default_factory=dict)
    driver: str | None = None          # default: the channel's own temperature node
    t0_c: float = 25.0


class InstallationEffect(_Strict):
    """Channel input rate = M @ body rate (cross-axis coupling / misalignment; seed 000 eq 1)."""

    matrix: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


class CrossChannelTemperature(_Strict):
    source_channel: str
    dph_per_c: float


class TimeDriftEffect(_Strict):
    """bias += dph_per_h * hours since clock_start (aging / linear drift)."""

    dph_per_h: dict[str, float]


class Sinusoid(_Strict):
    channel: str
    amplitude_dph: float
    period_s: float = Field(gt=0)
    phase_rad: float = 0.0


class RandomSteps(_Strict):
    """Bias steps at Poisson times (``rate_per_h``), normal amplitudes (``sigma_dph``)."""

    channels: list[str]
    rate_per_h: float = Field(gt=0)
    sigma_dph: float = Field(gt=0)


class UnexplainedEffect(_Strict):
    """Disturbances tied to no recorded signal (for honesty tests of the residual diagnosis)."""

    sinusoids: list[Sinusoid] = Field(default_factory=list)
    random_steps: RandomSteps | None = None


class Effects(_Strict):
    thermal_lag: ThermalLagEffect | None = None
    hysteresis: HysteresisEffect | None = None
    warmup: WarmupEffect | None = None
    g_sensitivity: GSensitivityEffect | None = None
    scale_factor_temperature: ScaleFactorEffect | None = None
    installation: InstallationEffect | None = None
    cross_channel_temperature: dict[str, CrossChannelTemperature] | None = None
    time_drift: TimeDriftEffect | None = None
    unexplained: UnexplainedEffect | None = None


class GaussMarkov(_Strict):
    sigma_dph: float = Field(ge=0)      # stationary standard deviation
    tau_s: float = Field(gt=0)          # correlation time


class ChannelNoise(_Strict):
    arw_deg_rt_h: float = Field(0.0, ge=0)          # white rate noise: ADEV(tau) = 60*ARW/sqrt(tau s) deg/h
    gauss_markov: list[GaussMarkov] = Field(default_factory=list)   # bias-instability model
    rrw_dph_rt_h: float = Field(0.0, ge=0)          # rate random walk, deg/h/sqrt(h)


class HrgModel(_Strict):
    """Resonance frequency per channel: cubic of the sensing-element temperature (seed 002 eq 2)
    plus a per-channel offset (seed 002 Table 1: the three resonators differ by ~8 and ~195 Hz)."""

    coefficients: tuple[float, float, float, float] = HRG_F2_COEFFS     # a3, a2, a1, a0
    # per-channel cubic replacing ``coefficients`` (e.g. refitted to Table 1 for Gy, Gz)
    channel_coefficients: dict[str, tuple[float, float, float, float]] = Field(default_factory=dict)
    offsets_hz: dict[str, float] = Field(default_factory=dict)
    noise_hz: float = Field(0.003, ge=0)     # white frequency noise per output sample


class Scenario(_Strict):
    name: str = "scenario"
    description: str = ""
    gyro_type: Literal["rlg", "fog", "hrg", "mems"]
    latitude_deg: float = Field(45.75, ge=-90, le=90)
    channels: tuple[str, ...] = ("x", "y", "z")
    thermal: ThermalNetwork
    probes: dict[str, str]                         # probe position name -> node it is glued to
    channel_nodes: dict[str, str]                  # channel -> its own temperature node/probe
    # channel -> the probe (a ``probes`` name) that reads that channel's own temperature: what the bench
    # config and each run declare (``gyro.channel_probes``) so that fits use t_i for channel i (S000 eq 4)
    channel_probes: dict[str, str] | None = None
    sensor_node: str                               # node read by the gyro's internal temperature
    sensing_nodes: dict[str, str] | None = None    # channel -> sensing element node (HRG frequency)
    bias: dict[str, ChannelBias]
    effects: Effects = Effects()
    noise: dict[str, ChannelNoise] = Field(default_factory=dict)
    accel_noise_g: float = Field(0.0, ge=0)
    hrg: HrgModel | None = None
    startup_invalid_s: float = Field(0.0, ge=0)   # status "invalid" for this long after power-on
    seed: int = 0

    @field_validator("channels")
    @classmethod
    def _three_channels(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if len(v) != 3 or len(set(v)) != 3:
            raise ValueError("exactly three distinct channel names are needed (body x, y, z)")
        return v

    # -- validation across sections ------------------------------------------------------------

    def channel_probe_map(self) -> dict[str, str]:
        """Channel -> its own probe: ``channel_probes`` as declared, else, per channel, the one probe
        glued to the channel's own node (channels without exactly one such probe are left out)."""
        if self.channel_probes is not None:
            return dict(self.channel_probes)
        out = {}
        for ch in self.channels:
            node = self.node_of(self.channel_nodes[ch])
            on_node = [p for p, n in self.probes.items() if n == node]
            if len(on_node) == 1:
                out[ch] = on_node[0]
        return out

    def temperature_names(self) -> set[str]:
        return set(self.thermal.nodes) | set(self.probes)

    def node_of(self, name: str) -> str:
        """Thermal node behind a node or probe name."""
        return self.probes.get(name, name)

    @model_validator(mode="after")
    def _cross_check(self) -> "Scenario":
        names = self.temperature_names()
        chans = set(self.channels)

        def need_channels(where: str, keys) -> None:
            for k in keys:
                if k not in chans:
                    raise ValueError(f"{where}: unknown channel {k!r} (channels: {', '.join(self.channels)})")

        def need_name(where: str, n: str) -> None:
            if n not in names:
                raise ValueError(f"{where}: unknown node or probe {n!r} (known: {', '.join(sorted(names))})")

        for probe, node in self.probes.items():
            if node not in self.thermal.nodes:
                raise ValueError(f"probes.{probe}: unknown thermal node {node!r}")
            if probe in self.thermal.nodes and node != probe:
                raise ValueError(f"probes.{probe}: a probe named like a node must sit on that node")
        need_channels("channel_nodes", self.channel_nodes)
        for ch in self.channels:
            if ch not in self.channel_nodes:
                raise ValueError(f"channel_nodes: channel {ch!r} missing")
            need_name(f"channel_nodes.{ch}", self.channel_nodes[ch])
        need_name("sensor_node", self.sensor_node)
        if self.channel_probes is not None:
            need_channels("channel_probes", self.channel_probes)
            for ch, probe in self.channel_probes.items():
                if probe not in self.probes:
                    raise ValueError(f"channel_probes.{ch}: {probe!r} is not a probe (probes: "
                                     f"{', '.join(sorted(self.probes)) or 'none'})")
        need_channels("bias", self.bias)
        for ch, spec in self.bias.items():
            for term in spec.terms:
                try:
                    parse_term(term, names)
                except ValueError as exc:
                    raise ValueError(f"bias.{ch}.terms.{term}: {exc}") from None
        need_channels("noise", self.noise)
        eff = self.effects
        if eff.thermal_lag and eff.thermal_lag.channels:
            need_channels("effects.thermal_lag.channels", eff.thermal_lag.channels)
        if eff.hysteresis:
            need_name("effects.hysteresis.driver", eff.hysteresis.driver)
            need_channels("effects.hysteresis.amplitude_dph", eff.hysteresis.amplitude_dph)
        if eff.warmup:
            need_channels("effects.warmup.amplitude_dph", eff.warmup.amplitude_dph)
        if eff.g_sensitivity:
            need_channels("effects.g_sensitivity.dph_per_g", eff.g_sensitivity.dph_per_g)
        if eff.scale_factor_temperature:
            sf = eff.scale_factor_temperature
            need_channels("effects.scale_factor_temperature.ppm", sf.ppm)
            need_channels("effects.scale_factor_temperature.ppm_per_c", sf.ppm_per_c)
            if sf.driver is not None:
                need_name("effects.scale_factor_temperature.driver", sf.driver)
        if eff.cross_channel_temperature:
            need_channels("effects.cross_channel_temperature", eff.cross_channel_temperature)
            for ch, cc in eff.cross_channel_temperature.items():
                need_channels(f"effects.cross_channel_temperature.{ch}.source_channel", [cc.source_channel])
                if cc.source_channel == ch:
                    raise ValueError(f"effects.cross_channel_temperature.{ch}: source must be another channel")
        if eff.time_drift:
            need_channels("effects.time_drift.dph_per_h", eff.time_drift.dph_per_h)
        if eff.unexplained:
            need_channels("effects.unexplained.sinusoids", [s.channel for s in eff.unexplained.sinusoids])
            if eff.unexplained.random_steps:
                need_channels("effects.unexplained.random_steps.channels", eff.unexplained.random_steps.channels)
        if self.gyro_type == "hrg":
            if self.hrg is None:
                raise ValueError("hrg: an HRG scenario needs the 'hrg' section (frequency model)")
            if self.sensing_nodes is None:
                raise ValueError("sensing_nodes: an HRG scenario needs channel -> resonator node")
            need_channels("hrg.offsets_hz", self.hrg.offsets_hz)
            need_channels("hrg.channel_coefficients", self.hrg.channel_coefficients)
        elif self.hrg is not None:
            raise ValueError(f"hrg: only allowed for gyro_type 'hrg', not {self.gyro_type!r}")
        if self.sensing_nodes is not None:
            need_channels("sensing_nodes", self.sensing_nodes)
            for ch in self.channels:
                if ch not in self.sensing_nodes:
                    raise ValueError(f"sensing_nodes: channel {ch!r} missing")
                need_name(f"sensing_nodes.{ch}", self.sensing_nodes[ch])
        return self

    # -- I/O -------------------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str | Path) -> "Scenario":
        """Load a scenario JSON file.  Errors: DataFormatError naming file, line/column or key."""
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise DataFormatError("scenario file not found", source=str(path)) from None
        return cls.from_json_text(text, source=str(path))

    @classmethod
    def from_json_text(cls, text: str, source: str = "<scenario>") -> "Scenario":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})",
                                  line=exc.lineno, source=source) from None
        return cls.from_dict(data, source=source)

    @classmethod
    def from_dict(cls, data: Any, source: str = "<scenario>") -> "Scenario":
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            first = exc.errors()[0]
            key = ".".join(str(p) for p in first["loc"])
            if first["type"] == "extra_forbidden":
                msg = f"unknown key {key!r}"
            elif key:
                msg = f"key {key!r}: {first['msg']}"
            else:
                msg = first["msg"]
            raise DataFormatError(msg, source=source) from None

    @classmethod
    def builtin(cls, name: str) -> "Scenario":
        """One of the shipped example scenarios (``default``, ``hrg``, ``fog_effects``)."""
        path = SCENARIO_DIR / f"{name}.json"
        if not path.exists():
            have = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.json")))
            raise DataFormatError(f"no built-in scenario {name!r} (have: {have})", source=str(SCENARIO_DIR))
        return cls.load(path)

    def with_changes(self, **changes: Any) -> "Scenario":
        """A validated copy with top-level fields replaced (e.g. ``noise={}`` for noise-free runs)."""
        data = self.model_dump()
        data.update(changes)
        return Scenario.from_dict(data, source=f"{self.name} (modified)")

    def truth(self) -> dict[str, Any]:
        """True values in a form tests can compare with fitted coefficients.

        ``channels[ch]``: intercept_dph, t0_c, terms (term text -> deg/h per unit), own temperature
        name, noise; ``effects``: the switched-on effects with their parameters; ``hrg``: the
        frequency model.  Bias is in deg/h on the channel axis, Earth rate *not* included.
        """
        chans = {}
        for ch in self.channels:
            b = self.bias.get(ch, ChannelBias())
            chans[ch] = {
                "intercept_dph": b.intercept_dph,
                "t0_c": b.t0_c,
                "terms": dict(b.terms),
                "temperature": self.channel_nodes[ch],
                "probe": self.channel_probe_map().get(ch),
                "noise": self.noise.get(ch, ChannelNoise()).model_dump(),
            }
        effects = {k: v for k, v in self.effects.model_dump().items() if v is not None}
        return {
            "gyro_type": self.gyro_type,
            "latitude_deg": self.latitude_deg,
            "probes": dict(self.probes),
            "channels": chans,
            "effects": effects,
            "hrg": None if self.hrg is None else {**self.hrg.model_dump(), "sensing_nodes": dict(self.sensing_nodes or {})},
        }
