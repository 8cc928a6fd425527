"""The WebSocket protocol's client messages (`/api/runs/{id}/stream`), as pydantic models: one
discriminated union on `type`, so a malformed message is refused with the field it got wrong,
and the protocol reads in one place. Server → client messages are listed in
`routers/stream.py`; the binary splat buffers in `kgs_core.splat_buffer`."""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError


class ClientMessage(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Subscribe(ClientMessage):
    """Send the static set (once, and again after a τ change or an edit), then answer time
    requests with dynamic sets."""

    type: Literal["subscribe"]
    lod: int | None = None  # 1-based; None: the run's finest. The run checks it against its levels.
    velocity: bool = True  # append velocities to dynamic sets (for the ellipsoid overlay)
    sh: bool = False  # also send the level's view-dependent colour (SH) coefficients, once


class TimeRequest(ClientMessage):
    """The dynamic set at `t`. Requests that arrive while one is computed coalesce: the latest
    wins, and its `seq` is echoed in the `answered` message."""

    type: Literal["time"]
    t: float = Field(ge=0.0, le=1.0)
    exposure: float = Field(0.0, ge=0.0, le=1.0)
    seq: int | None = None


class SetTau(ClientMessage):
    """Re-decompose at τ; every subscriber of the run gets the new sets."""

    type: Literal["tau"]
    tau: float = Field(gt=0.0)


class Ping(ClientMessage):
    type: Literal["ping"]


AnyClientMessage = Annotated[Union[Subscribe, TimeRequest, SetTau, Ping], Field(discriminator="type")]
_adapter = TypeAdapter(AnyClientMessage)


def parse_client_message(text: str) -> Subscribe | TimeRequest | SetTau | Ping:
    """The message in `text`; raises ValueError naming the field at fault."""
    try:
        return _adapter.validate_json(text)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "message"
        raise ValueError(f"{where}: {err['msg']}") from None
