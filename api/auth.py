"""Bearer-token authentication with three roles.

Tokens come from ``BENCH_TOKENS``: ``role:token`` pairs separated by commas, e.g.
``viewer:v-secret,operator:o-secret,admin:a-secret`` (a role may have several tokens).  Roles are
ordered: ``viewer`` reads; ``operator`` also starts / stops / pauses runs and fits models; ``admin``
also accepts fits as a gyro's coefficients.  Requests send ``Authorization: Bearer <token>``;
only ``/health`` and the API documentation answer without one.
"""
from __future__ import annotations

import hmac
from dataclasses import dataclass

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from api.problems import Problem

ROLES = ("viewer", "operator", "admin")
ENV_TOKENS = "BENCH_TOKENS"


@dataclass(frozen=True)
class Principal:
    role: str
    name: str          # "<role>#<n>": who did it, for the records, without the secret

    def allows(self, role: str) -> bool:
        return ROLES.index(self.role) >= ROLES.index(role)


def parse_tokens(text: str | None) -> dict[str, str]:
    """``"viewer:abc,operator:def"`` -> {token: role}.  Raises ValueError naming the bad pair."""
    tokens: dict[str, str] = {}
    for i, part in enumerate((text or "").split(","), start=1):
        part = part.strip()
        if not part:
            continue
        role, sep, token = part.partition(":")
        role, token = role.strip(), token.strip()
        if not sep or role not in ROLES:
            raise ValueError(f"{ENV_TOKENS} pair {i} ({role or part!r}): expected role:token with role one of "
                             f"{', '.join(ROLES)}")
        if len(token) < 8:
            raise ValueError(f"{ENV_TOKENS} pair {i} ({role}): token shorter than 8 characters")
        if token in tokens and tokens[token] != role:
            raise ValueError(f"{ENV_TOKENS} pair {i}: the same token is given for two roles")
        tokens[token] = role
    return tokens


def tokens_from_env() -> dict[str, str]:
    from bench.settings import load_settings

    return parse_tokens(load_settings().tokens)


_bearer = HTTPBearer(auto_error=False, description="A token from BENCH_TOKENS (role:token pairs)")


async def _principal(request: Request, creds: HTTPAuthorizationCredentials | None = Depends(_bearer)) -> Principal:
    tokens: dict[str, str] = request.app.state.tokens
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise Problem(401, "Authentication required",
                      "send 'Authorization: Bearer <token>' with a token from BENCH_TOKENS"
                      + ("" if tokens else " (none is configured on this server)"),
                      headers={"WWW-Authenticate": "Bearer"})
    given = creds.credentials.encode()
    for n, (token, role) in enumerate(tokens.items(), start=1):
        if hmac.compare_digest(given, token.encode()):
            return Principal(role=role, name=f"{role}#{n}")
    raise Problem(401, "Unknown token", "the bearer token is not one of the configured tokens"
                  + ("" if tokens else " (none is configured on this server: set BENCH_TOKENS)"),
                  headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})


def require(role: str):
    """Dependency: the caller's principal, which must have at least ``role``."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}")

    async def dependency(principal: Principal = Depends(_principal)) -> Principal:
        if not principal.allows(role):
            raise Problem(403, "Not allowed", f"this needs the {role} role; your token has the {principal.role} role")
        return principal

    dependency.required_role = role       # read by api.problems.document_problems
    return dependency
