"""Access control. On loopback (the default) the API is open to the local user unless a token
is set; binding any other address requires a token (generated and printed by `kgs-app serve`).
The token is accepted as `Authorization: Bearer …`, an `X-KGS-Token` header or a `token` query
parameter (browsers cannot set headers on WebSockets)."""

from __future__ import annotations

import secrets

from fastapi import HTTPException, Request, WebSocket


def _presented(headers, query) -> str | None:
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return headers.get("x-kgs-token") or query.get("token")


def token_ok(expected: str | None, presented: str | None) -> bool:
    if not expected:
        return True
    return presented is not None and secrets.compare_digest(presented.encode(), expected.encode())


def require_token(request: Request) -> None:
    expected = request.app.state.settings.token
    if not token_ok(expected, _presented(request.headers, request.query_params)):
        raise HTTPException(status_code=401, detail="missing or wrong access token",
                            headers={"WWW-Authenticate": "Bearer"})


async def websocket_token_ok(ws: WebSocket) -> bool:
    return token_ok(ws.app.state.settings.token, _presented(ws.headers, ws.query_params))
