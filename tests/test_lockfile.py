"""Reproducible installs: constraints.txt pins every package, satisfies the declared requirements, and
is what scripts/install.sh (the CI install) and the Dockerfile install with - this environment must
hold exactly the pinned versions."""
from __future__ import annotations

import re
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]


def pins() -> dict[str, str]:
    out = {}
    for n, line in enumerate((REPO / "constraints.txt").read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9.+!-]+)", line)
        assert m, f"constraints.txt line {n}: {line!r} is not 'name==version'"
        name = canonicalize_name(m.group(1))
        assert name not in out, f"constraints.txt line {n}: {name} pinned twice"
        out[name] = m.group(2)
    return out


def requirements() -> list[Requirement]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in project.get("optional-dependencies", {}).values():
        reqs += [Requirement(r) for r in extra]
    return reqs


def test_constraints_pin_every_requirement_within_its_range():
    p = pins()
    assert "gyrobench" not in p, "the project itself is not pinned"
    for req in requirements():
        name = canonicalize_name(req.name)
        assert name in p, f"{req.name} is required but not pinned in constraints.txt"
        assert Version(p[name]) in req.specifier, f"{req.name}=={p[name]} is outside {req.specifier}"


def test_this_environment_was_installed_with_the_constraints():
    """The CI install (scripts/install.sh) used constraints.txt: every pinned package that is installed
    has the pinned version, and every package the project needs is installed."""
    p = pins()
    installed = {canonicalize_name(d.metadata["Name"]): d.version for d in metadata.distributions()}
    wrong = {n: (installed[n], v) for n, v in p.items() if n in installed and installed[n] != v}
    assert not wrong, f"installed versions differ from constraints.txt (installed, pinned): {wrong}"
    missing = [r.name for r in requirements() if canonicalize_name(r.name) not in installed]
    assert not missing, f"not installed: {missing}"


def test_install_script_and_image_use_the_constraints():
    install = (REPO / "scripts" / "install.sh").read_text()
    assert re.search(r"pip install [^\n]*-c constraints\.txt[^\n]*-e '\.\[test\]'", install)
    assert (REPO / ".ci" / "run").read_text().count("scripts/install.sh") == 1
    docker = (REPO / "Dockerfile").read_text()
    assert "COPY pyproject.toml README.md constraints.txt ./" in docker
    assert "pip install -c constraints.txt ." in docker
    assert "constraints.txt" not in (REPO / ".dockerignore").read_text().split()


def test_w1thermsensor_is_a_test_dependency_only():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert not any(Requirement(r).name == "w1thermsensor" for r in project["dependencies"])
    assert any(Requirement(r).name == "w1thermsensor" for r in project["optional-dependencies"]["test"])
    users = [p.relative_to(REPO).as_posix() for d in ("bench", "api", "procedures") for p in (REPO / d).rglob("*.py")
             if re.search(r"^\s*(import|from)\s+w1thermsensor", p.read_text(), re.M)]
    assert users == [], f"product code imports w1thermsensor: {users}"
