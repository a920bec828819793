"""Formula terms: parse ``t1 + t1^2 + dt1 + (t1-t3) + t1*dt1`` into a design-matrix builder.

Grammar (whitespace ignored; positions in errors are 1-based character columns)::

    formula := term ('+' term)*              top level: '+' separates regressors (an intercept is
                                             always added; a lone '1' term is accepted and ignored)
    term    := product
    product := power ('*' power)*
    power   := primary ('^' INTEGER>=1)?
    primary := ATOM | NUMBER | '(' expr ')'
    expr    := product (('+'|'-') product)*  inside parentheses '+'/'-' are arithmetic,
                                             so (t1-t3) is a gradient and (t1-25)^2 a centred square

A top-level ``-`` is refused (write a gradient as ``(a-b)``).

Atoms resolve against the dataset columns, in this order:
``X`` -> ``temp_X`` if that column exists (a temperature, C);
``dX`` -> the rate of ``temp_X`` in C/min if ``temp_X`` exists (column ``rate_X`` when present, e.g.
computed before averaging by ``prep.add_rates``; otherwise computed with
``bench.signal.temperature_rate(time_s, temp_X, rate_window_s, method="centred_slope")``);
otherwise the column named ``X`` itself (e.g. ``lag_t1_600`` added by the close-loop helper, ``chamber_pv``).

The channel's own probe: ``tc`` stands for it and ``dtc`` for its rate, anywhere an atom may stand
(``tc^2``, ``(tc-t4)``, ``(tc-25)*dtc``).  They are resolved per channel when the formula is compiled
(``channel_probe="t2"``: ``tc`` -> ``temp_t2``, ``dtc`` -> dT2/dt), so the resolved terms and the
export name the real probe; a formula with ``tc`` compiled without a channel probe is refused, and so
is data with a probe literally named ``tc``.

Each parsed node is a JSON-able dict, which is also the firmware evaluation recipe::

    {"op": "temp",   "column": "temp_t1"}                        value of the column (C)
    {"op": "rate",   "column": "temp_t1", "window_s": 120.0}     dT/dt in C/min (centred LS slope)
    {"op": "column", "column": "lag_t1_600"}                     value of the column
    {"op": "const",  "value": 25.0}
    {"op": "add"|"sub"|"mul", "args": [a, b]}
    {"op": "pow",    "args": [a], "exp": 3}

Public API::

    parse_formula(text) -> list[Node]           (unresolved: atoms are {"op": "atom", "name": ...})
    compile_formula(text, columns, *, rate_window_s=120.0, target_unit="deg/h", channel_probe=None)
        -> CompiledFormula
    compile_terms(terms: list[(coef_name, expr_text)], columns, ..., channel_probe=None) -> CompiledFormula
    uses_channel_probe(text) -> bool            (does the formula say ``tc`` / ``dtc``?)
    CompiledFormula.design(ds, clip=None) -> (X with intercept column first, flagged bool array)
    CompiledFormula.signal_ranges(ds) -> {signal_key: [min, max]}
    evaluate_node(node, signals: dict[key, array]) -> array;  node_text(node) -> str
    FormulaError(BenchError) with .position
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from bench.errors import BenchError
from bench.fit.base import Dataset
from bench.signal import temperature_rate

Node = dict[str, Any]
CHANNEL_PROBE = "tc"                    # placeholder: the channel's own probe (``dtc``: its rate)
_TOKEN = re.compile(r"\s*(?:(?P<num>\d+(?:\.\d*)?(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)"
                    r"|(?P<id>[A-Za-z_][A-Za-z0-9_]*)|(?P<op>[-+*^()]))")
_COLUMN_UNITS = {"chamber_pv": "C", "chamber_sp": "C", "table_rate_dps": "deg/s", "power": "1", "time_s": "s"}
_PREFIX_UNITS = {"gyro_": "deg/h", "temp_": "C", "freq_": "Hz", "rate_": "C/min", "lag_": "C"}


# limits, the same for the CLI, the API and procedure parameters (a formula beyond them is refused)
MAX_FORMULA_CHARS = 300       # characters
MAX_DEPTH = 16                # nesting of parentheses
MAX_EXPONENT = 9              # t1^9: beyond that the powers of a temperature are numerically meaningless
MAX_CONSTANT = 1e6            # |number| in a formula


class FormulaError(BenchError):
    """A formula that cannot be parsed or resolved; ``position`` is the 1-based character column."""

    def __init__(self, text: str, position: int | None, message: str) -> None:
        where = f" at position {position}" if position is not None else ""
        pointer = f"\n  {text}\n  {' ' * (position - 1)}^" if position is not None else ""
        super().__init__(f"formula {text!r}: {message}{where}{pointer}")
        self.position = position
        self.formula = text


# ------------------------------------------------------------------------------------------- parser
class _Parser:
    def __init__(self, text: str) -> None:
        if len(text) > MAX_FORMULA_CHARS:
            raise FormulaError(text[:40] + "...", None, f"{len(text)} characters; at most {MAX_FORMULA_CHARS}")
        self.text = text
        self.depth = 0
        self.tokens: list[tuple[str, str, int]] = []
        pos = 0
        while pos < len(text):
            if text[pos:].strip() == "":
                break
            m = _TOKEN.match(text, pos)
            if not m or m.end() == pos:
                bad = pos + len(text[pos:]) - len(text[pos:].lstrip())
                raise FormulaError(text, bad + 1, f"unexpected character {text[bad]!r}")
            kind = m.lastgroup
            start = m.start(kind)
            self.tokens.append((kind, m.group(kind), start + 1))
            pos = m.end()
        self.i = 0

    def peek(self) -> tuple[str, str, int] | None:
        return self.tokens[self.i] if self.i < len(self.tokens) else None

    def take(self) -> tuple[str, str, int]:
        tok = self.peek()
        if tok is None:
            raise FormulaError(self.text, len(self.text) + 1, "unexpected end of formula")
        self.i += 1
        return tok

    def error(self, tok: tuple[str, str, int] | None, message: str) -> FormulaError:
        pos = tok[2] if tok else len(self.text) + 1
        return FormulaError(self.text, pos, message)

    def formula(self) -> list[tuple[Node, int]]:
        if not self.tokens:
            raise FormulaError(self.text, 1, "empty formula")
        terms = []
        while True:
            tok = self.peek()
            terms.append((self.product(), tok[2] if tok else len(self.text) + 1))
            tok = self.peek()
            if tok is None:
                return terms
            if tok[1] == "+":
                self.take()
                continue
            if tok[1] == "-":
                raise self.error(tok, "'-' between terms: write a gradient as (a-b); terms are joined by '+'")
            raise self.error(tok, f"expected '+' or end, found {tok[1]!r}")

    def expr(self) -> Node:
        node = self.product()
        while (tok := self.peek()) is not None and tok[1] in "+-" and tok[0] == "op":
            self.take()
            node = {"op": "add" if tok[1] == "+" else "sub", "args": [node, self.product()]}
        return node

    def product(self) -> Node:
        node = self.power()
        while (tok := self.peek()) is not None and tok[1] == "*":
            self.take()
            node = {"op": "mul", "args": [node, self.power()]}
        return node

    def power(self) -> Node:
        node = self.primary()
        tok = self.peek()
        if tok is not None and tok[1] == "^":
            self.take()
            exp_tok = self.peek()
            if exp_tok is None or exp_tok[0] != "num" or not re.fullmatch(r"\d+", exp_tok[1]) or int(exp_tok[1]) < 1:
                raise self.error(exp_tok, "exponent must be a whole number >= 1")
            if int(exp_tok[1]) > MAX_EXPONENT:
                raise self.error(exp_tok, f"exponent {exp_tok[1]} is above the limit of {MAX_EXPONENT}")
            self.take()
            node = {"op": "pow", "args": [node], "exp": int(exp_tok[1])}
        return node

    def primary(self) -> Node:
        tok = self.peek()
        if tok is None:
            raise self.error(None, "expected a signal, number or '(' but the formula ends")
        kind, value, _pos = tok
        if kind == "id":
            self.take()
            return {"op": "atom", "name": value}
        if kind == "num":
            if not abs(float(value)) <= MAX_CONSTANT:
                raise self.error(tok, f"number {value} is beyond the limit of +-{MAX_CONSTANT:g}")
            self.take()
            return {"op": "const", "value": float(value)}
        if value == "(":
            self.depth += 1
            if self.depth > MAX_DEPTH:
                raise self.error(tok, f"parentheses nested deeper than {MAX_DEPTH}")
            self.take()
            node = self.expr()
            self.depth -= 1
            close = self.peek()
            if close is None or close[1] != ")":
                raise self.error(close, "missing ')'")
            self.take()
            return node
        raise self.error(tok, f"expected a signal, number or '(' but found {value!r}")


def parse_formula(text: str) -> list[Node]:
    """Parse formula text into unresolved term trees (intercept not included; '1' terms dropped)."""
    parser = _Parser(text)
    terms = []
    seen: dict[str, int] = {}
    for node, pos in parser.formula():
        if node["op"] == "const":
            if node["value"] == 1.0:
                continue
            raise FormulaError(text, pos, "a constant term is not a regressor (the intercept is always included)")
        key = node_text(node)
        if key in seen:
            raise FormulaError(text, pos, f"term {key!r} appears twice")
        seen[key] = pos
        terms.append(node)
    return terms


# -------------------------------------------------------------------------------------- rendering
def node_text(node: Node) -> str:
    """Canonical text of a node (round-trips through ``parse_formula``)."""
    op = node["op"]
    if op == "atom":
        return node["name"]
    if op in ("temp", "rate", "column"):
        return node["name"]
    if op == "const":
        v = node["value"]
        return repr(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))
    if op in ("add", "sub"):
        a, b = node["args"]
        left = node_text(a)
        if a["op"] in ("add", "sub") and left.startswith("(") and left.endswith(")"):
            left = left[1:-1]
        return f"({left}{'+' if op == 'add' else '-'}{node_text(b)})"
    if op == "mul":
        return "*".join(node_text(a) for a in node["args"])
    if op == "pow":
        (a,) = node["args"]
        base = node_text(a)
        if a["op"] in ("mul", "pow"):
            base = f"({base})"
        return f"{base}^{node['exp']}"
    raise ValueError(f"unknown node op {op!r}")


# ------------------------------------------------------------------------------------- resolution
def _column_unit(name: str) -> str:
    if name in _COLUMN_UNITS:
        return _COLUMN_UNITS[name]
    for prefix, unit in _PREFIX_UNITS.items():
        if name.startswith(prefix):
            return unit
    return "?"


def resolve_atom(name: str, columns: Iterable[str], rate_window_s: float) -> Node:
    cols = set(columns)
    if f"temp_{name}" in cols:
        return {"op": "temp", "name": name, "column": f"temp_{name}", "unit": "C"}
    if name.startswith("d") and f"temp_{name[1:]}" in cols:
        return {"op": "rate", "name": name, "column": f"temp_{name[1:]}", "unit": "C/min",
                "window_s": float(rate_window_s), "precomputed": f"rate_{name[1:]}"}
    if name in cols:
        return {"op": "column", "name": name, "column": name, "unit": _column_unit(name)}
    raise KeyError(name)


def _placeholder_target(name: str, channel_probe: str | None, columns: set[str], text: str) -> str | None:
    """``tc`` -> the channel probe's name, ``dtc`` -> ``d<probe>``; None for any other atom."""
    if name not in (CHANNEL_PROBE, f"d{CHANNEL_PROBE}"):
        return None
    pos = _atom_position(text, name)
    if f"temp_{CHANNEL_PROBE}" in columns:
        raise FormulaError(text, pos, f"{name!r} is the placeholder for the channel's own probe, but the data "
                                      f"has a probe named {CHANNEL_PROBE!r}: rename that probe")
    if channel_probe is None:
        raise FormulaError(text, pos, f"{name!r} stands for the channel's own probe, and none is known here "
                                      "(fit per channel: the data's channel_probes metadata or probe=...)")
    if f"temp_{channel_probe}" not in columns:
        temps = sorted(c[5:] for c in columns if c.startswith("temp_"))
        raise FormulaError(text, pos, f"{name!r}: the channel's probe {channel_probe!r} has no column "
                                      f"temp_{channel_probe} (probes: {', '.join(temps) or 'none'})")
    return channel_probe if name == CHANNEL_PROBE else f"d{channel_probe}"


def _refuse_zero_differences(node: Node, original: Node, text: str, channel_probe: str | None) -> None:
    """A difference of a signal with itself (``(tc-t4)`` on a channel whose probe is t4) is a column of
    zeros, not a regressor: refuse it by name."""
    if node["op"] == "sub" and node_text(node["args"][0]) == node_text(node["args"][1]):
        said, means = node_text(original), node_text(node)
        where = f" (the channel's probe is {channel_probe!r})" if said != means else ""
        raise FormulaError(text, None, f"{said!r} is {means!r}{where}: identically zero, not a regressor")
    for sub, orig in zip(node.get("args", []), original.get("args", [])):
        _refuse_zero_differences(sub, orig, text, channel_probe)


def uses_channel_probe(text: str) -> bool:
    """True when the formula names the channel's own probe (``tc`` or ``dtc``)."""
    def walk(node: Node) -> bool:
        if node["op"] == "atom":
            return node["name"] in (CHANNEL_PROBE, f"d{CHANNEL_PROBE}")
        return any(walk(a) for a in node.get("args", []))
    return any(walk(t) for t in parse_formula(text))


def _resolve(node: Node, columns: set[str], rate_window_s: float, text: str,
             channel_probe: str | None = None) -> Node:
    if node["op"] == "atom":
        target = _placeholder_target(node["name"], channel_probe, columns, text)
        if target is not None:
            return resolve_atom(target, columns, rate_window_s)
        try:
            return resolve_atom(node["name"], columns, rate_window_s)
        except KeyError:
            pos = _atom_position(text, node["name"])
            temps = sorted(c[5:] for c in columns if c.startswith("temp_"))
            raise FormulaError(text, pos, f"unknown signal {node['name']!r} (no temp_{node['name']}, no column "
                                          f"{node['name']!r}; probes: {', '.join(temps) or 'none'})") from None
    out = dict(node)
    if "args" in node:
        out["args"] = [_resolve(a, columns, rate_window_s, text, channel_probe) for a in node["args"]]
    return out


def _atom_position(text: str, name: str) -> int | None:
    m = re.search(rf"(?<![A-Za-z0-9_]){re.escape(name)}(?![A-Za-z0-9_])", text)
    return m.start() + 1 if m else None


def node_unit(node: Node) -> str:
    op = node["op"]
    if op in ("temp", "rate", "column"):
        return node["unit"]
    if op == "const":
        return "1"
    if op in ("add", "sub"):
        units = {node_unit(a) for a in node["args"]} - {"1"}
        return units.pop() if len(units) == 1 else "?"
    if op == "mul":
        parts = [node_unit(a) for a in node["args"]]
        parts = [p for p in parts if p != "1"] or ["1"]
        return "*".join(parts)
    if op == "pow":
        u = node_unit(node["args"][0])
        return u if u == "1" else (f"{u}^{node['exp']}" if "/" not in u and "*" not in u else f"({u})^{node['exp']}")
    return "?"


def coefficient_unit(target_unit: str, term_unit: str) -> str:
    if term_unit == "1":
        return target_unit
    if re.fullmatch(r"[A-Za-z]+(\^\d+)?", term_unit):
        return f"{target_unit}/{term_unit}"
    return f"{target_unit}/({term_unit})"


def signal_key(node: Node) -> str:
    return f"{node['op']}:{node['column']}"


def leaves(node: Node) -> list[Node]:
    if node["op"] in ("temp", "rate", "column"):
        return [node]
    return [leaf for a in node.get("args", []) for leaf in leaves(a)]


def evaluate_node(node: Node, signals: dict[str, np.ndarray], cache: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """Evaluate a resolved node given the signal arrays keyed by ``signal_key``.

    ``cache`` (optional, keyed by canonical sub-expression text) shares common sub-expressions such
    as ``(t1-25)`` between the terms of one design matrix; integer powers use repeated products."""
    op = node["op"]
    if op in ("temp", "rate", "column"):
        return signals[signal_key(node)]
    if op == "const":
        return np.float64(node["value"])
    key = node_text(node) if cache is not None else None
    if key is not None and key in cache:
        return cache[key]
    if op == "pow":
        base = evaluate_node(node["args"][0], signals, cache)
        e = node["exp"]
        if e == 1:
            out = base
        elif e == 2:
            out = base * base
        elif e == 3:
            out = base * base * base
        else:
            out = base ** e
    else:
        a, b = (evaluate_node(x, signals, cache) for x in node["args"])
        if op == "add":
            out = a + b
        elif op == "sub":
            out = a - b
        elif op == "mul":
            out = a * b
        else:
            raise ValueError(f"unknown node op {op!r}")
    if key is not None:
        cache[key] = out
    return out


# ------------------------------------------------------------------------------------ compiled form
@dataclass
class CompiledFormula:
    """Resolved terms; ``names[0]`` is the intercept coefficient name."""

    text: str
    names: list[str]                   # coefficient names, intercept first
    terms: list[Node]                  # resolved term trees (without intercept)
    rate_window_s: float
    target_unit: str = "deg/h"
    units: dict[str, str] = field(default_factory=dict)

    @property
    def term_texts(self) -> list[str]:
        return [node_text(t) for t in self.terms]

    def signal_nodes(self) -> dict[str, Node]:
        out: dict[str, Node] = {}
        for t in self.terms:
            for leaf in leaves(t):
                out.setdefault(signal_key(leaf), leaf)
        return out

    def signals(self, ds: Dataset) -> dict[str, np.ndarray]:
        """Raw (unclipped) signal arrays for every leaf."""
        out: dict[str, np.ndarray] = {}
        for key, leaf in self.signal_nodes().items():
            if leaf["op"] == "rate":
                pre = leaf.get("precomputed")
                if pre and pre in ds:
                    out[key] = np.asarray(ds[pre], dtype=np.float64)
                else:
                    out[key] = temperature_rate(ds.time, ds[leaf["column"]], leaf["window_s"], method="centred_slope")
            else:
                out[key] = np.asarray(ds[leaf["column"]], dtype=np.float64)
        return out

    def signal_ranges(self, ds: Dataset) -> dict[str, list[float]]:
        return {k: [float(np.nanmin(v)), float(np.nanmax(v))] for k, v in self.signals(ds).items()}

    def design(self, ds: Dataset, clip: dict[str, list[float]] | None = None,
               signals: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Design matrix (n, 1 + len(terms)), intercept column first, and a ``flagged`` array: True
        where a signal lies outside ``clip`` (key -> [lo, hi]); those signals are clipped first."""
        sig = dict(self.signals(ds) if signals is None else signals)
        n = len(ds)
        flagged = np.zeros(n, dtype=bool)
        if clip:
            for key, (lo, hi) in clip.items():
                if key in sig:
                    v = sig[key]
                    flagged |= (v < lo) | (v > hi)
                    sig[key] = np.clip(v, lo, hi)
        x = np.empty((n, 1 + len(self.terms)), order="F")
        x[:, 0] = 1.0
        cache: dict[str, np.ndarray] = {}
        for j, term in enumerate(self.terms, start=1):
            x[:, j] = evaluate_node(term, sig, cache)
        return x, flagged

    def recipe(self) -> list[dict[str, Any]]:
        """Term list for the export: coefficient name, expression text, unit and tree."""
        rows = [{"coefficient": self.names[0], "expr": "1", "tree": {"op": "const", "value": 1.0},
                 "unit": self.units.get(self.names[0], self.target_unit)}]
        for name, term in zip(self.names[1:], self.terms):
            rows.append({"coefficient": name, "expr": node_text(term), "tree": _clean_tree(term),
                         "unit": self.units.get(name, "")})
        return rows


def _clean_tree(node: Node) -> Node:
    drop = ("name", "unit", "precomputed")
    out = {k: v for k, v in node.items() if k not in drop} if node["op"] != "const" else dict(node)
    if node["op"] in ("temp", "rate", "column"):
        out["signal"] = node["name"]
    if "args" in node:
        out["args"] = [_clean_tree(a) for a in node["args"]]
    return out


def compile_terms(terms: list[tuple[str, str]], columns: Iterable[str], *, rate_window_s: float = 120.0,
                  target_unit: str = "deg/h", intercept: str = "intercept", text: str | None = None,
                  channel_probe: str | None = None) -> CompiledFormula:
    """Compile named terms [(coefficient_name, expression)] (each expression one formula term;
    ``tc``/``dtc`` resolve to ``channel_probe``)."""
    cols = set(columns)
    names, nodes, units = [intercept], [], {intercept: target_unit}
    for name, expr in terms:
        parsed = parse_formula(expr)
        if len(parsed) != 1:
            raise FormulaError(expr, None, "each named term must be a single term")
        node = _resolve(parsed[0], cols, rate_window_s, expr, channel_probe)
        _refuse_zero_differences(node, parsed[0], expr, channel_probe)
        names.append(name)
        nodes.append(node)
        units[name] = coefficient_unit(target_unit, node_unit(node))
    full = text if text is not None else " + ".join(e for _, e in terms)
    return CompiledFormula(full, names, nodes, float(rate_window_s), target_unit, units)


def compile_formula(text: str, columns: Iterable[str], *, rate_window_s: float = 120.0,
                    target_unit: str = "deg/h", channel_probe: str | None = None) -> CompiledFormula:
    """Parse and resolve a user formula; coefficient names are the canonical term texts as written
    (``tc^2`` stays the name; its resolved term, e.g. ``t2^2``, is in the recipe).  ``tc``/``dtc``
    resolve to ``channel_probe``."""
    cols = set(columns)
    parsed = parse_formula(text)
    nodes = [_resolve(p, cols, rate_window_s, text, channel_probe) for p in parsed]
    seen: dict[str, str] = {}
    for p, node in zip(parsed, nodes):
        _refuse_zero_differences(node, p, text, channel_probe)
        resolved = node_text(node)
        if resolved in seen:
            raise FormulaError(text, _atom_position(text, CHANNEL_PROBE), f"terms {seen[resolved]!r} and "
                               f"{node_text(p)!r} are the same term {resolved!r} on this channel (its probe is "
                               f"{channel_probe!r})")
        seen[resolved] = node_text(p)
    names = ["intercept"] + [node_text(p) for p in parsed]
    units = {"intercept": target_unit}
    for name, node in zip(names[1:], nodes):
        units[name] = coefficient_unit(target_unit, node_unit(node))
    return CompiledFormula(text, names, nodes, float(rate_window_s), target_unit, units)


def compiled_from_recipe(recipe: list[dict[str, Any]], text: str, rate_window_s: float,
                         target_unit: str = "deg/h") -> CompiledFormula:
    """Rebuild a ``CompiledFormula`` from ``CompiledFormula.recipe()`` (as stored in a FitResult)."""
    names = [r["coefficient"] for r in recipe]
    terms = [_restore_tree(r["tree"]) for r in recipe[1:]]
    units = {r["coefficient"]: r.get("unit", "") for r in recipe}
    return CompiledFormula(text, names, terms, float(rate_window_s), target_unit, units)


def _restore_tree(node: Node) -> Node:
    out = dict(node)
    if node["op"] in ("temp", "rate", "column"):
        out["name"] = node["signal"]
        out["unit"] = {"temp": "C", "rate": "C/min"}.get(node["op"], _column_unit(node["column"]))
        if node["op"] == "rate":
            out["precomputed"] = "rate_" + node["column"][len("temp_"):]
    if "args" in node:
        out["args"] = [_restore_tree(a) for a in node["args"]]
    return out

