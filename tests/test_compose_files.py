"""Static checks of docker-compose.yml and the Dockerfile (no Docker engine runs here).

* the compose file parses and validates against the Compose Specification with ``compose_spec``
  (PyPI ``compose-spec``: bindings of the Rust ``compose_spec`` crate, a typed parser that refuses
  unknown keys, bad durations, bad depends_on conditions...) after YAML merge keys are applied;
* cross-references the spec parser leaves to the engine: depends_on targets exist, ``service_healthy``
  targets have a healthcheck, ``service_completed_successfully`` targets are one-shot, named volumes
  are declared, ``network_mode: service:X`` names a service, build contexts hold a Dockerfile whose
  COPY sources exist;
* every command (service commands, ``sh -c`` scripts, healthchecks) exists: ``bench ...`` is parsed by
  the Typer app's own click commands (unknown commands, options or bad values fail), ``uvicorn`` by
  uvicorn's click command with its ``module:attr`` resolved, ``python -c`` code compiled and its
  imports resolved; other programs must be ones the python:3.11-slim image has;
* the wiring: the API has the tokens, everything that opens the database has a URL pointing at the
  postgres service with its user and database, the worker reads the endpoints file the simulator writes
  on a volume both mount at the same path, for the bench name the simulator uses;
* the image installs the package with ``pip install .``, so the data files the services read
  (dashboard pages, migration scripts, simulator scenarios) must be package data.
"""
from __future__ import annotations

import importlib
import inspect
import re
import shlex
import tomllib
from fnmatch import fnmatch
from pathlib import Path
from urllib.parse import urlsplit

import click
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
COMPOSE = REPO / "docker-compose.yml"
DOCKERFILE = REPO / "Dockerfile"
# programs other than bench / python / uvicorn the commands may use: all in python:3.11-slim (Debian)
BASE_IMAGE_PROGRAMS = {"sh", "rm", "mkdir", "test", "true", "echo", "cat"}
OUR_IMAGE = "gyrobench:latest"
try:                       # Typer >= 0.2x vendors its own click: its errors are not click's
    from typer._click.exceptions import UsageError as _TyperUsageError
    USAGE_ERRORS: tuple[type[Exception], ...] = (click.UsageError, _TyperUsageError)
except ImportError:
    USAGE_ERRORS = (click.UsageError,)
_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:?[-?])([^}]*))?\}")


def interpolate(text: str) -> str:
    """Compose variable interpolation with every variable unset: ``${V:-default}`` -> default;
    ``${V:?message}`` (required) -> a placeholder value; ``${V}`` -> empty."""
    def sub(m: re.Match) -> str:
        op, arg = m.group(2), m.group(3)
        if op in (":-", "-"):
            return arg
        if op in (":?", "?"):
            return f"required-{m.group(1).lower()}"
        return ""
    return _VAR.sub(sub, text)


@pytest.fixture(scope="module")
def compose() -> dict:
    from compose_spec import PyOptions

    text = COMPOSE.read_text()
    # the engine interpolates variables before it validates (a port's host address may be a variable)
    parsed = PyOptions(apply_merge=True).from_yaml(interpolate(text))   # raises ValueError naming the bad key
    parsed.validate()                                        # references to volumes / networks / configs
    doc = yaml.safe_load(text)                               # uninterpolated, merge keys applied
    for name, svc in parsed.to_dict()["services"].items():
        assert set(svc) <= set(doc["services"][name]) | {"environment"}, name
        raw_env = doc["services"][name].get("environment") or {}
        assert {k: interpolate(str(v)) for k, v in raw_env.items()} == \
            {k: str(v) for k, v in (svc.get("environment") or {}).items()}, name
        doc["services"][name]["environment"] = raw_env
    return doc


def services(doc: dict) -> dict[str, dict]:
    return doc["services"]


def our_services(doc: dict) -> dict[str, dict]:
    return {n: s for n, s in services(doc).items() if s.get("image") == OUR_IMAGE or "build" in s}


def test_compose_spec_parser_refuses_what_it_should():
    """The validator used here is not a rubber stamp: a misspelt key and a bad condition fail."""
    from compose_spec import PyOptions

    text = COMPOSE.read_text()
    for bad in (text.replace("healthcheck:", "helthcheck:", 1),
                text.replace("service_healthy", "service_happy", 1),
                text.replace("interval: 2s", "interval: soon", 1)):
        with pytest.raises(ValueError):
            PyOptions(apply_merge=True).from_yaml(bad).validate()


def test_services_and_cross_references(compose):
    svcs = services(compose)
    assert {"postgres", "api", "worker", "sim", "migrate"} <= set(svcs)
    assert svcs["postgres"]["image"].startswith("postgres:")
    declared_volumes = set(compose.get("volumes") or {})
    for name, svc in svcs.items():
        assert "image" in svc or "build" in svc, f"{name}: neither image nor build"
        if "build" in svc:
            context = svc["build"] if isinstance(svc["build"], str) else svc["build"].get("context", ".")
            dockerfile = "Dockerfile" if isinstance(svc["build"], str) else svc["build"].get("dockerfile", "Dockerfile")
            assert (REPO / context / dockerfile).is_file(), f"{name}: build context {context} has no {dockerfile}"
        deps = svc.get("depends_on") or {}
        deps = {d: {"condition": "service_started"} for d in deps} if isinstance(deps, list) else deps
        for dep, spec in deps.items():
            assert dep in svcs, f"{name}: depends_on unknown service {dep}"
            cond = spec.get("condition", "service_started")
            if cond == "service_healthy":
                assert "healthcheck" in svcs[dep], f"{name} waits for {dep} healthy but {dep} has no healthcheck"
            if cond == "service_completed_successfully":
                assert svcs[dep].get("restart", "no") == "no", f"{dep} must be one-shot (restart: \"no\")"
        for vol in svc.get("volumes") or []:
            source = vol.split(":", 1)[0] if isinstance(vol, str) else vol.get("source")
            if source and not source.startswith((".", "/", "~")):
                assert source in declared_volumes, f"{name}: volume {source} not declared at top level"
            elif source:
                assert (REPO / source).exists(), f"{name}: bind-mount source {source} does not exist"
        mode = svc.get("network_mode", "")
        if mode.startswith("service:"):
            target = mode.split(":", 1)[1]
            assert target in svcs, f"{name}: network_mode names unknown service {target}"
            assert target in deps, f"{name}: shares {target}'s network, so must depend on it"
            assert "ports" not in svc, f"{name}: a service on another's network cannot publish ports"
    # the API and the database start only after the migration; the worker too
    for name in ("api", "worker"):
        assert (svcs[name]["depends_on"].get("migrate") or {}).get("condition") == "service_completed_successfully"
    assert svcs["migrate"]["depends_on"]["postgres"]["condition"] == "service_healthy"


def test_environment_wiring(compose):
    svcs = services(compose)
    pg_env = svcs["postgres"]["environment"]
    for name, svc in our_services(compose).items():
        if name == "sim":
            continue                      # the simulator opens no database
        url = interpolate(str(svc["environment"].get("BENCH_DATABASE_URL", "")))
        parts = urlsplit(url)
        assert parts.scheme == "postgresql+psycopg", f"{name}: BENCH_DATABASE_URL {url!r}"
        assert parts.hostname == "postgres" and (parts.port or 5432) == 5432, f"{name}: {url!r}"
        assert parts.username == pg_env["POSTGRES_USER"] and parts.path.lstrip("/") == pg_env["POSTGRES_DB"]
        assert parts.password == interpolate(str(pg_env["POSTGRES_PASSWORD"]))
    tokens = str(svcs["api"]["environment"]["BENCH_TOKENS"])
    assert tokens.startswith("${BENCH_TOKENS:?"), "BENCH_TOKENS must come from the environment, with no default secret"
    port = svcs["api"]["command"][svcs["api"]["command"].index("--port") + 1]
    assert any(str(p).endswith(f":{port}") for p in svcs["api"]["ports"])


def test_secrets_are_required_and_the_api_is_local_by_default(compose):
    """No known default password; the API is published on the loopback interface unless told otherwise."""
    svcs = services(compose)
    for name, svc in svcs.items():
        for key, value in (svc.get("environment") or {}).items():
            for m in _VAR.finditer(str(value)):
                if m.group(1) in ("POSTGRES_PASSWORD", "BENCH_TOKENS"):
                    assert m.group(2) in (":?", "?"), f"{name}.{key}: ${{{m.group(1)}}} must be required, not defaulted"
    assert "${POSTGRES_PASSWORD:?" in str(svcs["postgres"]["environment"]["POSTGRES_PASSWORD"])
    for name, svc in svcs.items():
        for spec in svc.get("ports", []):
            text = interpolate(str(spec)) if isinstance(spec, str) else spec
            if isinstance(text, dict):
                host_ip = interpolate(str(text.get("host_ip", "")))
            else:
                parts = text.split(":")
                assert len(parts) == 3, f"{name}: port {spec!r} publishes on every interface; give a host address"
                host_ip = parts[0]
            assert host_ip == "127.0.0.1", f"{name}: port {spec!r} is published on {host_ip!r} by default"


def _bench_app():
    import typer

    from bench.cli import app
    return typer.main.get_command(app)


def _pending(ctx) -> list[str]:
    """The words a group context left for its subcommand (click keeps the subcommand's name apart)."""
    protected = getattr(ctx, "protected_args", None) or getattr(ctx, "_protected_args", None) or []
    return list(protected) + list(ctx.args)


def _is_group(cmd) -> bool:
    return hasattr(cmd, "resolve_command")


def check_bench(args: list[str]):
    """Parse ``bench ARGS`` with the CLI's own (click) commands; returns the leaf command's context."""
    group = _bench_app()
    ctx = group.make_context("bench", list(args))
    cmd = group
    rest = _pending(ctx)
    while _is_group(cmd):
        assert rest, f"bench {' '.join(args)}: no subcommand"
        name, sub, rest = cmd.resolve_command(ctx, rest)
        assert sub is not None, f"bench {' '.join(args)}: unknown command {name}"
        ctx = sub.make_context(name, rest, parent=ctx)
        cmd = sub
        rest = _pending(ctx) if _is_group(cmd) else ctx.args
    assert not ctx.args, f"bench {' '.join(args)}: unexpected arguments {ctx.args}"
    return ctx


def check_uvicorn(args: list[str]) -> click.Context:
    main = importlib.import_module("uvicorn.main").main
    ctx = main.make_context("uvicorn", list(args))
    module, _, attr = ctx.params["app"].partition(":")
    target = getattr(importlib.import_module(module), attr)
    assert callable(target), f"uvicorn app {ctx.params['app']} is not callable"
    if ctx.params.get("factory"):
        assert not inspect.signature(target).parameters or all(
            p.default is not p.empty for p in inspect.signature(target).parameters.values())
    return ctx


def check_python_code(code: str) -> None:
    import ast

    tree = ast.parse(code)
    compile(tree, "<compose python -c>", "exec")
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            mod = importlib.import_module(node.module)
            for alias in node.names:
                assert hasattr(mod, alias.name) or importlib.util.find_spec(f"{node.module}.{alias.name}"), \
                    f"python -c: {node.module} has no {alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                importlib.import_module(alias.name)


def check_command(argv: list[str], where: str) -> list[tuple[str, object]]:
    """Check one command line; returns [(program, parsed context or None)] for each program run."""
    argv = [interpolate(a) for a in argv]
    if argv and argv[0] == "exec":
        argv = argv[1:]
    prog, args = argv[0], argv[1:]
    if prog == "bench":
        return [("bench", check_bench(args))]
    if prog == "uvicorn":
        return [("uvicorn", check_uvicorn(args))]
    if prog == "python":
        assert args[0] == "-c", f"{where}: python must run code with -c"
        check_python_code(args[1])
        return [("python", None)]
    if prog == "sh":
        assert args[0] == "-c", f"{where}: sh must run a script with -c"
        out = []
        for part in re.split(r"&&|\|\||;", args[1]):
            out += check_command(shlex.split(part), where)
        return out
    assert prog in BASE_IMAGE_PROGRAMS, f"{where}: program {prog!r} is not in the image"
    return [(prog, None)]


def test_every_command_exists_in_the_cli(compose):
    parsed = {}
    for name, svc in our_services(compose).items():
        cmd = svc["command"]
        argv = cmd if isinstance(cmd, list) else shlex.split(cmd)
        parsed[name] = check_command(argv, f"{name}.command")
        hc = (svc.get("healthcheck") or {}).get("test")
        if hc:
            kind, rest = hc[0], hc[1:]
            check_command(rest if kind == "CMD" else ["sh", "-c", rest[0]], f"{name}.healthcheck")
    # the simulator writes the endpoints file the worker reads, on a volume both mount at the same place
    sim_ctx = dict(parsed["sim"])["bench"]
    worker_ctx = dict(parsed["worker"])["bench"]
    assert sim_ctx.info_name == "up" and worker_ctx.info_name == "worker"
    endpoints = sim_ctx.params["endpoints_json"]
    assert worker_ctx.params["config"] == endpoints
    mounts = {s: {v.split(":")[1]: v.split(":")[0] for v in services(compose)[s]["volumes"]} for s in ("sim", "worker")}
    mount_dir = str(Path(endpoints).parent)
    assert mounts["sim"].get(mount_dir) and mounts["sim"][mount_dir] == mounts["worker"].get(mount_dir)
    # the DS18B20 tree the simulator creates under TMPDIR must be on that volume too (the worker reads it)
    assert services(compose)["sim"]["environment"]["TMPDIR"].startswith(mount_dir + "/")
    # the worker serves the bench the simulator describes
    from bench.sim.bench import SimulatedBench
    default_name = inspect.signature(SimulatedBench.__init__).parameters["bench_name"].default
    assert worker_ctx.params["bench"] == default_name
    assert services(compose)["worker"]["network_mode"] == "service:sim"


def test_bench_cli_refuses_unknown_commands_and_options():
    """check_bench really parses: a typo in a command or an option fails."""
    with pytest.raises(USAGE_ERRORS):
        check_bench(["sim", "upp"])
    with pytest.raises(USAGE_ERRORS):
        check_bench(["worker", "--bench", "sim1", "--confg", "x.json"])
    with pytest.raises(USAGE_ERRORS):
        check_bench(["sim", "up", "--speed", "fast"])
    with pytest.raises(USAGE_ERRORS):
        check_uvicorn(["--factory", "api.app:app_from_env", "--prot", "8000"])


def test_dockerfile_base_install_and_copied_sources():
    text = DOCKERFILE.read_text()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.strip().startswith("#")]
    assert lines[0] == "FROM python:3.11-slim"
    assert re.search(r"pip install -c constraints\.txt \.(\s|$)", text), \
        "the image installs the package from the source tree with the pinned versions"
    for ln in lines:
        if ln.startswith("COPY "):
            for src in shlex.split(ln)[1:-1]:
                assert (REPO / src).exists(), f"Dockerfile copies {src}, which does not exist"
    ignored = (REPO / ".dockerignore").read_text().split()
    assert ".venv/" in ignored and ".git/" in ignored


def test_package_data_ships_the_files_the_services_read():
    """``pip install .`` copies only Python modules unless data files are declared package data."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text()).get("tool", {}).get("setuptools", {})
    package_data: dict[str, list[str]] = config.get("package-data", {})
    manifest = (REPO / "MANIFEST.in").read_text() if (REPO / "MANIFEST.in").exists() else ""
    missing = []
    for folder in ("api/dashboard/static", "bench/sim/scenarios", "bench/storage/migrations"):
        for path in sorted((REPO / folder).rglob("*")):
            if not path.is_file() or path.suffix in (".py", ".pyc") or "__pycache__" in path.parts:
                continue
            rel = path.relative_to(REPO)
            covered = any(
                rel.as_posix().startswith(pkg.replace(".", "/") + "/")
                and any(fnmatch(rel.relative_to(pkg.replace(".", "/")).as_posix(), pat) for pat in pats)
                for pkg, pats in package_data.items()) or any(
                pkg == "*" and any(fnmatch(rel.name, pat) for pat in pats) for pkg, pats in package_data.items())
            if not covered and rel.as_posix() not in manifest and rel.parent.as_posix() not in manifest:
                missing.append(rel.as_posix())
    assert not missing, ("not package data, so missing from the image (add to [tool.setuptools.package-data] "
                         f"in pyproject.toml): {missing}")
