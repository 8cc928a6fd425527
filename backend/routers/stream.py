"""WebSocket `/api/runs/{id}/stream`: splat buffers for scrubbing, live τ, training progress.

Client → server (JSON text; the models, with their bounds, in `backend/messages.py`):
* `{"type": "subscribe", "lod": L | null, "velocity": true, "sh": false}`: send the static set
  (once; with `sh`, then the level's view-dependent colour coefficients), then answer time
  requests with dynamic sets.
* `{"type": "time", "t": 0.42, "exposure": 0, "seq": 17}`: the dynamic set at `t`. Requests that
  arrive while one is being computed coalesce: only the latest is answered (its `seq` is echoed).
* `{"type": "tau", "tau": 2e-5}`: recompute the decomposition (every subscriber gets the new sets).
* `{"type": "ping"}`: answered with `{"type": "pong"}`.

Server → client: binary buffers (layout in `kgs_core.splat_buffer`), and JSON text messages
`{"type": "progress", …}` (while the run trains, once a second), `{"type": "status", …}`,
`{"type": "decomposition", …}` (after τ changes and edits) and `{"type": "error", "message": …}`.
"""

from __future__ import annotations

import asyncio
import json
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from functools import partial

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool

from ..messages import Ping, SetTau, Subscribe, TimeRequest, parse_client_message
from ..registry import ACTIVE
from ..security import websocket_token_ok

router = APIRouter(tags=["stream"])
MAX_MESSAGE = 64 * 1024
# Text messages waiting for a client. One that stops reading while it keeps sending (a ping
# flood) would otherwise grow this without bound: past the limit it is disconnected.
MAX_NOTES = 256
SLOW_CONSUMER = 4008  # close code: the client did not read its messages
# Splat buffers are built on two threads of their own, not on the shared threadpool: 50
# clients asking at once would otherwise run 40 builds side by side on two cores, each a
# millisecond of numpy, and spend more time handing the interpreter lock and the view's lock
# around than building (measured: docs/serve.md, "Where the buffers are built").
BUFFER_THREADS = ThreadPoolExecutor(max_workers=2, thread_name_prefix="kgs-buffers")


async def build(fn, *args):
    return await asyncio.get_running_loop().run_in_executor(BUFFER_THREADS, partial(fn, *args))


class Hub:
    """Who watches which run, so τ changes and edits reach every viewer."""

    def __init__(self):
        self.subs: dict[str, set] = defaultdict(set)

    async def broadcast(self, run_id: str, msg: dict) -> None:
        for conn in list(self.subs.get(run_id, ())):
            conn.notify(msg)


class Connection:
    def __init__(self, ws: WebSocket, run_id: str):
        self.ws, self.run_id = ws, run_id
        self.lod: int | None = None
        self.velocity = True
        self.sh = False
        self.sh_sent = False
        self.subscribed = False
        self.static_version = -1
        self.pending: dict | None = None  # latest time request (coalesced)
        self.last_time: dict | None = None
        self.notes: list[dict] = []
        self.overflow = False  # set when notes passed MAX_NOTES: the sender closes the socket
        self.wake = asyncio.Event()
        self.view = None  # the RunView last served, reused while the server keeps it loaded

    def notify(self, msg: dict) -> None:
        if msg.get("type") == "pong" and any(n.get("type") == "pong" for n in self.notes):
            return  # one unanswered pong says all there is to say
        if len(self.notes) >= MAX_NOTES:
            self.overflow = True
            self.wake.set()
            return
        self.notes.append(msg)
        if msg.get("type") == "decomposition" and self.last_time is not None and self.pending is None:
            self.pending = dict(self.last_time)  # the dynamic set changed: resend it
        self.wake.set()


def _error(message: str) -> dict:
    return {"type": "error", "message": message}


async def receiver(conn: Connection, app) -> None:
    while True:
        message = await conn.ws.receive()
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000))
        text = message.get("text")
        if text is None:  # a binary frame: this protocol has none from the client
            conn.notify(_error("binary messages are not part of this protocol; send JSON text"))
            continue
        if len(text) > MAX_MESSAGE:
            conn.notify(_error(f"message larger than {MAX_MESSAGE} bytes ignored"))
            continue
        try:
            msg = parse_client_message(text)
        except ValueError as exc:
            conn.notify(_error(f"bad message: {exc}"))
            continue
        try:
            if isinstance(msg, Subscribe):
                conn.lod, conn.velocity, conn.sh = msg.lod, msg.velocity, msg.sh
                conn.sh_sent = False
                conn.subscribed = True
                conn.static_version = -1
                conn.wake.set()
            elif isinstance(msg, TimeRequest):
                conn.pending = {"t": msg.t, "exposure": msg.exposure, "seq": msg.seq}  # the latest wins
                conn.wake.set()
            elif isinstance(msg, SetTau):
                from ..deps import run_view

                view = run_view(app, conn.run_id)
                decomposition = await run_in_threadpool(view.set_tau, msg.tau)
                await app.state.hub.broadcast(conn.run_id, {"type": "decomposition", **decomposition})
            elif isinstance(msg, Ping):
                conn.notify({"type": "pong"})
        except (KeyError, TypeError, ValueError) as exc:
            conn.notify(_error(f"bad {msg.type!r} message: {exc}"))
        except Exception as exc:  # HTTPException from run_view (no model yet, ...)
            conn.notify(_error(getattr(exc, "detail", str(exc))))


async def sender(conn: Connection, app) -> None:
    from ..deps import run_view

    while True:
        await conn.wake.wait()
        conn.wake.clear()
        if conn.overflow:
            await conn.ws.close(code=SLOW_CONSUMER, reason=f"more than {MAX_NOTES} unread messages")
            return
        while conn.notes:
            await conn.ws.send_text(json.dumps(conn.notes.pop(0)))
        if not conn.subscribed:
            continue
        # Resolving a view asks the workspace database and the disk: once per connection, and
        # again only after the run was deleted or left the cache of loaded runs.
        view = conn.view if conn.view is not None and app.state.views.loaded(conn.run_id) is conn.view else None
        if view is None:
            try:
                view = conn.view = run_view(app, conn.run_id)
            except Exception as exc:
                conn.subscribed = False
                await conn.ws.send_text(json.dumps(_error(getattr(exc, "detail", str(exc)))))
                continue
        if conn.static_version != view.version:
            try:
                buf = await build(view.static_buffer, conn.lod)
            except ValueError as exc:  # an LoD level the run does not have
                conn.subscribed = False
                await conn.ws.send_text(json.dumps(_error(str(exc))))
                continue
            conn.static_version = view.version
            await conn.ws.send_bytes(buf)
        if conn.sh and not conn.sh_sent:
            conn.sh_sent = True
            sh = await build(view.sh_buffer, conn.lod)
            if sh is not None:
                await conn.ws.send_bytes(sh)
        if conn.pending is not None:
            req, conn.pending = conn.pending, None
            try:
                buf = await build(view.dynamic_buffer, req["t"], req["exposure"], conn.lod, conn.velocity)
            except ValueError as exc:
                await conn.ws.send_text(json.dumps(_error(str(exc))))
                continue
            conn.last_time = req
            await conn.ws.send_bytes(buf)
            if req.get("seq") is not None:
                await conn.ws.send_text(json.dumps({"type": "answered", "seq": req["seq"], "t": req["t"]}))
        if conn.pending is not None or conn.notes:
            conn.wake.set()


async def progress(conn: Connection, app) -> None:
    """While the run trains: its progress once a second, then its final status."""
    from .runs import public

    last = None
    while True:
        row = app.state.ws.get("runs", conn.run_id)
        if row is None:
            conn.notify(_error("the run was deleted"))
            return
        info = public(row)
        if info["status"] in ACTIVE:
            if info["progress"] and info["progress"] != last:
                last = info["progress"]
                conn.notify({"type": "progress", **info["progress"]})
        else:
            conn.notify({"type": "status", "status": info["status"], "error": info["error"], "has_model": info["has_model"]})
            return
        await asyncio.sleep(1.0)


@router.websocket("/api/runs/{run_id}/stream")
async def stream(ws: WebSocket, run_id: str) -> None:
    # Accepted, then closed with a code: a handshake refused before accepting reaches a
    # browser as close code 1006 with no reason (a real server answers it with an HTTP 403),
    # while 4401/4404 after accepting tell the page what went wrong. (Host and Origin are
    # refused at the handshake by HostOriginGuard: a cross-site page gets no connection.)
    await ws.accept()
    if not await websocket_token_ok(ws):
        await ws.close(code=4401, reason="missing or wrong access token")
        return
    app = ws.app
    if app.state.ws.get("runs", run_id) is None:
        await ws.close(code=4404, reason=f"no run with id {run_id!r}")
        return
    conn = Connection(ws, run_id)
    hub = app.state.hub
    hub.subs[run_id].add(conn)
    tasks = [asyncio.create_task(f(conn, app)) for f in (receiver, sender, progress)]
    try:
        done, _ = await asyncio.wait(tasks[:2], return_when=asyncio.FIRST_COMPLETED)
        for t in done:
            exc = t.exception()
            if exc and not isinstance(exc, (WebSocketDisconnect, RuntimeError)):
                raise exc
    finally:
        for t in tasks:
            t.cancel()
        hub.subs[run_id].discard(conn)
