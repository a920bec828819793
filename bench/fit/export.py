"""Versioned JSON export of fitted models, one document per gyro ID (``bench export``).

Document (schema ``gyrobench.fit.export``, ``schema_version`` 1)::

    {"schema": "gyrobench.fit.export", "schema_version": 1, "gyro_id": "...", "gyro_type": "...",
     "revision": 3, "created_utc": "2025-...Z", "source": {...}, "metrics": {...},
     "models": [{"model", "channel", "target", "definition", "coefficients", "units", "validity",
                 "stats", "evaluation": RECIPE or null}]}

``evaluation`` is an explicit recipe that firmware can follow without this code (linear models):

1. ``inputs``: each input signal with ``kind`` temp (the column, C), rate (dT/dt of the column in
   C/min: centred least-squares slope over ``filter.window_s`` seconds; a causal firmware may use the
   least-squares slope over the last window_s seconds, accepting a window_s/2 delay) or column (the
   raw column).  ``clip`` = [lo, hi]: clip the input to it; a sample with any clipped input is flagged.
2. ``terms``: bias = sum of ``value`` x term; each term is a ``tree`` of ops: temp/rate/column
   (the input named by ``column`` and op), const (``value``), add/sub/mul (two ``args``), pow (one arg
   raised to the integer ``exp``).  The intercept term is the constant 1.
3. ``hull`` (optional): (T, dT/dt) convex-hull vertices of the fit data for the inputs
   ``hull_inputs``; outside it the sample is flagged.
4. compensated rate = raw gyro output - bias (deg/h).

Files: ``<directory>/<gyro_id>.r<NNNN>.json``; ``save_export`` picks the next revision, writes
atomically and never overwrites.  ``load_export`` checks schema and version.
``evaluate_model_doc`` is a small reference evaluator that uses only the JSON (tests compare it to
``models.predict``).

Public API::

    build_export(gyro_id, results, *, gyro_type=None, metrics=None, source=None) -> dict
    save_export(doc, directory) -> Path
    load_export(path) -> dict
    latest_export(directory, gyro_id) -> Path | None
    results_from_export(doc) -> list[FitResult]     (to apply stored coefficients with models.predict)
    evaluate_model_doc(model_doc, columns, time_s=None) -> (values, flagged)
"""
from __future__ import annotations

import json
import os
import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from bench.errors import DataFormatError
from bench.files import temp_beside
from bench.fit.base import FitResult
from bench.jsonsafe import jsonable as _jsonable
from bench.signal import temperature_rate

SCHEMA = "gyrobench.fit.export"
SCHEMA_VERSION = 1
_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_OPS = {"temp", "rate", "column", "const", "add", "sub", "mul", "pow"}


def _check_id(gyro_id: str) -> str:
    if not isinstance(gyro_id, str) or not _ID_RE.match(gyro_id):
        raise DataFormatError(f"gyro id {gyro_id!r}: use 1-64 letters, digits, '.', '_' or '-'")
    return gyro_id


def evaluation_recipe(result: FitResult) -> dict[str, Any] | None:
    """Explicit evaluation recipe for a linear FitResult (None for other kinds unless the model's
    definition carries its own ``evaluation``)."""
    d = result.definition
    if d.get("kind") != "linear":
        return d.get("evaluation")
    clip = result.validity.get("signals", {})
    inputs: dict[str, dict[str, Any]] = {}

    def walk(node: dict[str, Any]) -> None:
        if node["op"] in ("temp", "rate", "column"):
            key = f"{node['op']}:{node['column']}"
            entry = {"key": key, "kind": node["op"], "column": node["column"], "name": node.get("signal"),
                     "unit": {"temp": "C", "rate": "C/min"}.get(node["op"], ""), "clip": clip.get(key)}
            if node["op"] == "rate":
                entry["filter"] = dict(d["rate_filter"])
            inputs.setdefault(key, entry)
        for a in node.get("args", []):
            walk(a)

    for term in d["terms"]:
        walk(term["tree"])
    terms = [{"coefficient": t["coefficient"], "value": result.coefficients[t["coefficient"]],
              "unit": result.units.get(t["coefficient"], t.get("unit", "")), "expr": t["expr"], "tree": t["tree"]}
             for t in d["terms"]]
    recipe: dict[str, Any] = {
        "output": "bias_dph", "inputs": list(inputs.values()), "terms": terms,
        "combine": "bias_dph = sum(term.value * evaluate(term.tree))",
        "compensated": f"{result.target} - bias_dph",
        "outside_validity": "clip each input to its clip range; flag the sample if an input was clipped or "
                            "(T, dT/dt) lies outside the hull",
        "ops": {"temp": "value of the column (C)", "rate": "dT/dt of the column in C/min (filter)",
                "column": "value of the column", "const": "the number 'value'", "add": "a + b", "sub": "a - b",
                "mul": "a * b", "pow": "a ** exp (integer)"},
    }
    if result.validity.get("hull"):
        recipe["hull"] = result.validity["hull"]
        recipe["hull_inputs"] = result.validity["hull_signals"]
    return recipe


def build_export(gyro_id: str, results: list[FitResult], *, gyro_type: str | None = None,
                 metrics: dict[str, Any] | None = None, source: dict[str, Any] | None = None) -> dict[str, Any]:
    _check_id(gyro_id)
    models = []
    for r in results:
        entry = r.to_json()
        entry["evaluation"] = _jsonable(evaluation_recipe(r))
        models.append(entry)
    return _jsonable({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "gyro_id": gyro_id,
                      "gyro_type": gyro_type, "revision": None,
                      "created_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                      "source": source or {}, "metrics": metrics or {}, "models": models})


def _revisions(directory: Path, gyro_id: str) -> list[tuple[int, Path]]:
    pat = re.compile(rf"^{re.escape(gyro_id)}\.r(\d{{4,}})\.json$")
    out = []
    if directory.is_dir():
        for p in directory.iterdir():
            m = pat.match(p.name)
            if m:
                out.append((int(m.group(1)), p))
    return sorted(out)


def latest_export(directory: str | os.PathLike, gyro_id: str) -> Path | None:
    revs = _revisions(Path(directory), _check_id(gyro_id))
    return revs[-1][1] if revs else None


def save_export(doc: dict[str, Any], directory: str | os.PathLike) -> Path:
    """Write ``doc`` as the next revision for its gyro id; returns the path."""
    gyro_id = _check_id(doc.get("gyro_id"))
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    revs = _revisions(directory, gyro_id)
    rev = (revs[-1][0] + 1) if revs else 1
    doc = dict(doc, revision=rev)
    text = json.dumps(doc, indent=2, allow_nan=False, sort_keys=False) + "\n"
    path = directory / f"{gyro_id}.r{rev:04d}.json"
    fd, tmp = temp_beside(path)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.link(tmp, path)           # fails if the revision appeared meanwhile: never overwrite
    finally:
        os.unlink(tmp)
    return path


def load_export(path: str | os.PathLike) -> dict[str, Any]:
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"not JSON: {exc.msg}", line=exc.lineno, source=str(path)) from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        raise DataFormatError(f"schema is not {SCHEMA!r}", source=str(path))
    if doc.get("schema_version") != SCHEMA_VERSION:
        raise DataFormatError(f"schema_version {doc.get('schema_version')!r} not supported (need {SCHEMA_VERSION})",
                              source=str(path))
    _check_id(doc.get("gyro_id"))
    for i, m in enumerate(doc.get("models", [])):
        ev = m.get("evaluation")
        if ev and "terms" in ev:
            for t in ev["terms"]:
                _check_tree(t["tree"], f"{path}: models[{i}] term {t.get('coefficient')!r}")
    return doc


def _check_tree(node: Any, where: str) -> None:
    if not isinstance(node, dict) or node.get("op") not in _OPS:
        raise DataFormatError(f"{where}: bad term tree node {node!r}")
    for a in node.get("args", []):
        _check_tree(a, where)


def evaluate_model_doc(model_doc: dict[str, Any], columns: dict[str, np.ndarray],
                       time_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Reference evaluation of one exported linear model from its JSON recipe only.

    ``columns``: column name -> array; rate inputs are taken from ``columns['rate:<column>']`` when
    given, else computed from ``time_s`` with the documented filter."""
    ev = model_doc.get("evaluation")
    if not ev or "terms" not in ev:
        raise DataFormatError(f"model {model_doc.get('model')!r} has no term recipe")
    signals: dict[str, np.ndarray] = {}
    unclipped: dict[str, np.ndarray] = {}
    n = None
    flagged = None
    for inp in ev["inputs"]:
        key = inp["key"]
        if inp["kind"] == "rate":
            if key in columns:
                v = np.asarray(columns[key], float)
            else:
                if time_s is None:
                    raise DataFormatError(f"rate input {key} needs time_s")
                v = temperature_rate(time_s, columns[inp["column"]], inp["filter"]["window_s"], method="centred_slope")
        else:
            v = np.asarray(columns[inp["column"]], float)
        unclipped[key] = v
        n = len(v)
        flagged = np.zeros(n, bool) if flagged is None else flagged
        if inp.get("clip"):
            lo, hi = inp["clip"]
            flagged |= (v < lo) | (v > hi)
            v = np.clip(v, lo, hi)
        signals[key] = v

    def ev_node(node: dict[str, Any]):
        op = node["op"]
        if op in ("temp", "rate", "column"):
            return signals[f"{op}:{node['column']}"]
        if op == "const":
            return node["value"]
        if op == "pow":
            return ev_node(node["args"][0]) ** node["exp"]
        a, b = ev_node(node["args"][0]), ev_node(node["args"][1])
        return a + b if op == "add" else a - b if op == "sub" else a * b

    total = 0.0
    for t in ev["terms"]:
        total = total + t["value"] * ev_node(t["tree"])
    values = np.broadcast_to(np.asarray(total, float), (n,)).copy() if n is not None else np.asarray(total)
    if flagged is None:
        flagged = np.zeros(len(values), bool)
    if ev.get("hull"):
        from bench.fit.models import inside_hull
        kt, kr = ev["hull_inputs"]
        raw_t = unclipped[kt]
        raw_r = unclipped[kr]      # the hull applies to the unclipped inputs
        pts = np.column_stack([raw_t, raw_r])
        finite = np.all(np.isfinite(pts), axis=1)
        inside = np.ones(len(values), bool)
        inside[finite] = inside_hull(ev["hull"], pts[finite])
        flagged |= ~inside
    return values, flagged


def results_from_export(doc: dict[str, Any]) -> list[FitResult]:
    """``FitResult`` objects of a loaded export document (for ``models.predict`` / ``compensate``)."""
    out = []
    for i, m in enumerate(doc.get("models", [])):
        try:
            out.append(FitResult(model=m["model"], channel=m["channel"], target=m["target"],
                                 definition=m["definition"], coefficients=m["coefficients"], units=m["units"],
                                 validity=m["validity"], stats=m.get("stats", {})))
        except KeyError as exc:
            raise DataFormatError(f"models[{i}] lacks {exc.args[0]!r}") from None
    return out
