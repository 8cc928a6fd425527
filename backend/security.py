"""Access control. On loopback (the default) the API is open to the local user unless a token
is set; binding any other address requires a token (generated and printed by `kgs-app serve`).
The token is accepted as `Authorization: Bearer …`, an `X-KGS-Token` header or a `token` query
parameter (browsers cannot set headers on WebSockets)."""

from __future__ import annotations

import re
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
        raise HTTPException(status_code=401, detail="missing or wrong access token", headers={"WWW-Authenticate": "Bearer"})


async def websocket_token_ok(ws: WebSocket) -> bool:
    return token_ok(ws.app.state.settings.token, _presented(ws.headers, ws.query_params))


# ---------------------------------------------------------------- Host and Origin

SAFE_METHODS = ("GET", "HEAD", "OPTIONS")
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")


def _hostname(host_header: str) -> str:
    """`example.org:8000` -> `example.org`, `[::1]:8000` -> `::1` (lower case)."""
    h = host_header.strip().lower()
    if h.startswith("["):
        return h[1 : h.find("]")] if "]" in h else h
    return h.rsplit(":", 1)[0] if h.count(":") == 1 else h


def host_allowed(host_header: str, bound: str, extra: list[str]) -> bool:
    """A Host header names this server: the bound address, a loopback name, or a name the user
    allowed (`--allow-host`). A page that rebinds its own DNS name to 127.0.0.1 sends its own
    name, so it is refused. Bound to every interface (`0.0.0.0`, `::`; a token is then
    required) any name passes unless the user listed some."""
    name = _hostname(host_header)
    allowed = {h.lower() for h in extra}
    if bound in WILDCARD_HOSTS and not allowed:
        return bool(name)
    return name in allowed | {bound.lower()} | set(LOOPBACK_NAMES)


def origin_allowed(origin: str | None, host_header: str, cors_origins: list[str]) -> bool:
    """An unsafe request or a WebSocket from a browser carries `Origin`: it must be this
    server's own page (same host and port as the request) or an origin the user allowed with
    `--cors`. No Origin at all is a non-browser client (curl, the desktop viewer)."""
    if origin is None:
        return True
    if origin in cors_origins:
        return True
    from urllib.parse import urlsplit

    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == host_header.strip().lower()


async def send_error(send, status: int, detail: str) -> None:
    """A JSON error response `{"detail": ...}` straight from ASGI middleware."""
    import json

    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
        }
    )
    await send({"type": "http.response.body", "body": body})


class HostOriginGuard:
    """ASGI middleware in front of everything (API, WebSockets, static files): a foreign Host
    gets 400 (DNS rebinding), a foreign Origin on a POST/PUT/PATCH/DELETE gets 403, and a
    WebSocket handshake with either is refused (cross-site requests that a browser sends
    without asking, which the token alone does not stop when no token is set)."""

    def __init__(self, app, settings):
        self.app, self.settings = app, settings

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        s = self.settings
        problem = None
        if not host_allowed(host, s.host, s.allowed_hosts):
            problem = (400, f"unknown Host {host!r}: this server answers to {s.host} and loopback names (add others with --allow-host)")
        elif (scope["type"] == "websocket" or scope.get("method", "GET") not in SAFE_METHODS) and not origin_allowed(
            headers.get("origin"), host, s.cors_origins
        ):
            problem = (403, f"cross-origin request from {headers.get('origin')!r} refused (allow an origin with --cors)")
        if problem is None:
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008, "reason": problem[1][:120]})
            return
        await send_error(send, *problem)


class BodyLimit:
    """ASGI middleware: a JSON body larger than MAX_JSON_BODY gets 413 before anything reads
    it (a 200 MB `POST /tau` was parsed whole), and one without a Content-Length gets 411.
    Uploads (a scene, and a second camera's video) have their own, streamed limit."""

    MAX_JSON_BODY = 1 << 20
    STREAMED = re.compile(r"^/api/scenes/(upload|[0-9a-f]{12}/video)$")

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in SAFE_METHODS or self.STREAMED.match(scope["path"]):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        length = headers.get("content-length")
        status = None
        if length is None:
            status = (411, "a request body needs a Content-Length") if "transfer-encoding" in headers else None
        elif not length.isdigit() or int(length) > self.MAX_JSON_BODY:
            status = (413, f"request body larger than {self.MAX_JSON_BODY} bytes")
        if status is None:
            return await self.app(scope, receive, send)
        await send_error(send, *status)
