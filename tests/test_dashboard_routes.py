"""The dashboard's pages and assets as served (no browser): every page renders with its script, every
asset is served with its media type and security headers, nothing is loaded from outside the server,
the JavaScript parses, and every API call the scripts make names an endpoint and query parameters the
API really has (so a renamed endpoint or parameter fails here, not in front of an operator)."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api import dashboard
from api.app import create_app
from bench.storage import open_database

STATIC = Path(dashboard.__file__).with_name("static")
PAGES = {"/ui/": "overview.js", "/ui/start": "start.js", "/ui/runs/7": "run.js", "/ui/gyros": "gyro.js",
         "/ui/gyros/RLG-7": "gyro.js", "/ui/fits/3": "fit.js", "/ui/close-loop": "closeloop.js",
         "/ui/close-loop/2": "closeloop.js"}


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    db = open_database(f"sqlite:///{tmp_path_factory.mktemp('dash') / 'r.sqlite'}")
    application = create_app(db, tokens="viewer:viewer-token-1")
    if not any(str(getattr(r, "path", "")).startswith("/ui") for r in application.routes):
        application.include_router(dashboard.router)
    yield application
    db.dispose()


@pytest.fixture(scope="module")
def client(app):
    return TestClient(app)


def test_pages_render_with_their_script_and_headers(client):
    for path, script in PAGES.items():
        r = client.get(path)
        assert r.status_code == 200, (path, r.text[:200])
        assert r.headers["content-type"].startswith("text/html")
        assert "default-src 'self'" in r.headers["content-security-policy"]
        assert r.headers["x-content-type-options"] == "nosniff"
        html = r.text
        assert "{{" not in html, f"{path}: unfilled template field"
        scripts = re.findall(r'<script src="/ui/static/([^"]+)"', html)
        assert scripts == ["common.js", "plot.js", script], (path, scripts)
    assert client.get("/ui", follow_redirects=False).headers["location"] == "/ui/"
    assert client.get("/ui/runs/not-a-number").status_code == 422


def test_assets_served_with_media_types_and_nothing_else(client):
    names = sorted(p.name for p in STATIC.iterdir() if p.is_file() and p.suffix != ".html")
    assert {"common.js", "plot.js", "app.css", "run.js", "start.js"} <= set(names)
    for name in names:
        r = client.get(f"/ui/static/{name}")
        assert r.status_code == 200, name
        expected = {".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}[Path(name).suffix]
        assert r.headers["content-type"].startswith(expected), (name, r.headers["content-type"])
        assert r.content == (STATIC / name).read_bytes()
    for bad in ("nope.js", "shell.html", "..%2F__init__.py", "%2e%2e/__init__.py", "../__init__.py"):
        r = client.get(f"/ui/static/{bad}")
        assert r.status_code == 404, bad
        if r.headers["content-type"].startswith("application/problem+json"):
            assert "detail" in r.json()


def test_no_external_resources():
    """Offline lab PC: no CDN, no web fonts, no absolute URL to anywhere (XML namespaces aside)."""
    for path in STATIC.iterdir():
        text = path.read_text(encoding="utf-8")
        for url in re.findall(r"(?:https?:)?//[A-Za-z0-9.-]+\.[A-Za-z]{2,}[^\s\"'`)]*", text):
            assert url.startswith("http://www.w3.org/"), f"{path.name}: external URL {url}"
        assert "@import" not in text and "@font-face" not in text, path.name


def _node() -> str | None:
    import playwright

    bundled = Path(playwright.__file__).parent / "driver" / "node"
    return str(bundled) if bundled.exists() else shutil.which("node")


def test_scripts_parse():
    node = _node()
    if node is None:
        pytest.skip("no JavaScript engine: neither playwright's bundled node nor node on PATH")
    for path in sorted(STATIC.glob("*.js")):
        r = subprocess.run([node, "--check", str(path)], capture_output=True, text=True, timeout=30)
        assert r.returncode == 0, f"{path.name}: {r.stderr}"


def test_plot_tick_labels_step_by_the_tick_step():
    """Each axis label is its tick's value: with a 0.025 step (an x axis of about 0.3 h, zoomed) the
    labels read 0.075, 0.100, 0.125 ..., never 0.08, 0.10, 0.13 (0.125 rounded to two decimals)."""
    node = _node()
    if node is None:
        pytest.skip("no JavaScript engine: neither playwright's bundled node nor node on PATH")
    script = """
      const vm = require("vm"), fs = require("fs");
      const lib = vm.runInNewContext(fs.readFileSync(process.argv[1], "utf8") + ";({niceTicks, tickLabel})", {});
      const out = [[0.07, 0.33, 12], [0, 0.35, 10], [10, 30, 10], [-30, 50, 6], [0, 2500, 10]].map(([lo, hi, n]) => {
        const t = lib.niceTicks(lo, hi, n);
        return [t.step, t.ticks.map((v) => lib.tickLabel(v, t.step))];
      });
      console.log(JSON.stringify(out));"""
    r = subprocess.run([node, "-e", script, str(STATIC / "plot.js")], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0, r.stderr
    import json

    axes = json.loads(r.stdout)
    assert axes[0] == [0.025, ["0.050", "0.075", "0.100", "0.125", "0.150", "0.175", "0.200", "0.225", "0.250",
                               "0.275", "0.300", "0.325", "0.350"]]
    for step, labels in axes:
        values = [float(v) for v in labels]
        assert all(abs((b - a) - step) < 1e-9 * max(1.0, step) for a, b in zip(values, values[1:])), (step, labels)
    assert axes[2][1][:3] == ["10", "12", "14"] and axes[3][1][:2] == ["-40", "-20"]


# ------------------------------------------------------------------------------ API calls of the pages
_CALL = re.compile(r"\b(?:api|apiFetch|downloadWithToken|followEvents)\(\s*([`\"])(/[^`\"]*)\1")


def api_calls() -> list[tuple[str, str, str]]:
    """(script, path template, query text) of each literal API call in the scripts."""
    out = []
    for path in sorted(STATIC.glob("*.js")):
        for m in _CALL.finditer(path.read_text(encoding="utf-8")):
            url = m.group(2)
            url = re.sub(r"\$\{query\}$", "?status=queued&limit=100", url)     # overview.js builds it in a variable
            route, _, query = url.partition("?")
            out.append((path.name, route, query))
    return out


def _matches(template: str, route: str) -> bool:
    """Does the API path ``template`` ("/runs/{run_id}/stop") fit the script's ``route``
    ("/runs/${RUN_ID}/${command}"): each ${...} of the script stands for one path segment."""
    pattern = "^" + re.sub(r"\\\$\\\{[^}]*\\\}", "[^/]+", re.escape(route)) + "$"
    return re.match(pattern, template) is not None


def test_every_api_call_of_the_pages_exists(app):
    spec = app.openapi()
    calls = api_calls()
    assert len(calls) >= 15, calls
    used = set()
    for script, route, query in calls:
        templates = [t for t in spec["paths"] if _matches(t, route)]
        assert templates, f"{script}: calls {route}, which the API does not have"
        if len(templates) == 1:
            used.add(templates[0])
        params = {p["name"] for t in templates for op in spec["paths"][t].values() for p in op.get("parameters", [])
                  if p["in"] == "query"}
        for name in re.findall(r"(?:^|&)([A-Za-z_]+)=", query):
            assert name in params, f"{script}: {route} has no query parameter {name!r} (has {sorted(params)})"
    # run controls are called as /runs/${RUN_ID}/${command} for each key of CONTROLS in run.js
    controls = re.findall(r"^  (\w+): \{ label:", (STATIC / "run.js").read_text(), flags=re.M)
    assert sorted(controls) == ["abort", "pause", "resume", "stop"]
    for command in controls:
        assert "post" in spec["paths"][f"/runs/{{run_id}}/{command}"]
    for needed in ("/runs", "/runs/{run_id}", "/runs/{run_id}/data", "/runs/{run_id}/events",
                   "/procedures", "/benches", "/gyros/{gyro_id}/coefficients", "/gyros/{gyro_id}/fits",
                   "/fits/{fit_id}/report", "/close-loop/{analysis_id}"):
        assert needed in used, f"no page calls {needed}"
