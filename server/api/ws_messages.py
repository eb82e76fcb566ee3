"""The teleop WebSocket's messages (``/api/v1/robots/{robot_id}/teleop``): one pydantic model per message
type, the parsing of what a client sends, and the JSON schemas the OpenAPI document publishes.

OpenAPI has no notion of a WebSocket, so the messages' schemas are merged into ``components.schemas``
(``add_to_openapi``) and ``PROTOCOL_MARKDOWN`` (the OpenAPI ``info.description``) names them. The
protocol in prose, with examples: docs/websocket.md.
"""

from __future__ import annotations

import json
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, RootModel, ValidationError
from pydantic.json_schema import models_json_schema

from server.api.schemas import RobotDetail, TeleopCommandIn

PATH = "/api/v1/robots/{robot_id}/teleop"
STATE_PERIOD_S = 0.1  # a state message every 0.1 s (10 Hz) on every open socket
CLOSE_UNKNOWN_ROBOT = 4404  # close code after the 404 error message for a robot that does not exist
REF_TEMPLATE = "#/components/schemas/{model}"


class TeleopErrorItem(BaseModel):
    """One problem with a message; the offending value is never echoed (NaN and infinities are not JSON)."""

    model_config = ConfigDict(extra="forbid")
    loc: list[str | int] = Field(..., description="where in the message: field names and list indices")
    msg: str
    type: str = Field(..., description="pydantic's error type, or json_invalid for a message that is not JSON")


class TeleopStateMessage(BaseModel):
    """Server to client, every 0.1 s: the robot's live state (the same body as ``GET /robots/{id}``)."""

    model_config = ConfigDict(extra="forbid")
    state: RobotDetail


class TeleopAcceptedMessage(BaseModel):
    """Server to client, the answer to an accepted command: it is applied exactly once, at the next control
    tick, composed with the other commands that arrived since the last tick."""

    model_config = ConfigDict(extra="forbid")
    accepted: Literal[True] = True
    pending: int = Field(..., ge=1, description="commands the next control tick applies, this one included")


class TeleopErrorMessage(BaseModel):
    """Server to client, the answer to a refused message (nothing changes, the socket stays open) or, with
    status 404, the only message before the close code 4404. ``status`` is the HTTP status the same
    refusal gets from ``POST /robots/{id}/command``."""

    model_config = ConfigDict(extra="forbid")
    error: str | list[TeleopErrorItem] = Field(
        ..., description="what went wrong: a sentence, or for status 422 the list of problems with the message"
    )
    status: int = Field(
        ...,
        ge=400,
        le=599,
        description="403 needs the operator role, 404 unknown robot, 409 not under teleop or not the lease "
        "holder, 413 message too large, 422 not a valid command, 429 over the per-step limits with the "
        "commands already waiting",
    )


class TeleopServerMessage(RootModel[TeleopStateMessage | TeleopAcceptedMessage | TeleopErrorMessage]):
    """Any message the server sends on the teleop socket: exactly one of the three types validates."""


CLIENT_MESSAGES: tuple[type[BaseModel], ...] = (TeleopCommandIn,)
SERVER_MESSAGES: tuple[type[BaseModel], ...] = (TeleopStateMessage, TeleopAcceptedMessage, TeleopErrorMessage)


def _problem(loc: list, msg: str, type_: str) -> TeleopErrorMessage:
    return TeleopErrorMessage(error=[TeleopErrorItem(loc=loc, msg=msg, type=type_)], status=422)


def read_command(message: dict, max_bytes: int) -> TeleopCommandIn | TeleopErrorMessage:
    """The command in one received ASGI ``websocket.receive`` message (JSON in a text frame, or UTF-8 JSON
    in a binary one), or the error to answer with."""
    raw = message.get("text")
    if raw is None:
        raw = message.get("bytes") or b""
    size = len(raw.encode()) if isinstance(raw, str) else len(raw)
    if size > max_bytes:
        return TeleopErrorMessage(error=f"message larger than {max_bytes} bytes", status=413)
    try:
        data = json.loads(raw)  # like the REST body: NaN and Infinity parse, and the model refuses them by name
    except json.JSONDecodeError as exc:
        return _problem([], f"Invalid JSON: {exc.msg}", "json_invalid")
    except (UnicodeDecodeError, RecursionError):
        return _problem([], "Invalid JSON: not UTF-8 text, or nested too deeply", "json_invalid")
    try:
        return TeleopCommandIn.model_validate(data)
    except ValidationError as exc:
        items = [TeleopErrorItem(loc=list(e["loc"]), msg=e["msg"], type=e["type"]) for e in exc.errors()]
        return TeleopErrorMessage(error=items, status=422)


def json_schemas() -> dict[str, dict]:
    """The JSON schemas of the socket's messages and of the models they contain, by component name, with
    references into ``#/components/schemas``."""
    models = [(m, "validation") for m in CLIENT_MESSAGES]
    models += [(m, "serialization") for m in (*SERVER_MESSAGES, TeleopServerMessage)]
    _, top = models_json_schema(models, ref_template=REF_TEMPLATE)
    return top["$defs"]


def add_to_openapi(openapi: dict) -> dict:
    """Adds the message schemas to an OpenAPI document's ``components.schemas``. A name the document already
    has (``RobotDetail``, ``TeleopCommandIn``: the REST routes use them too) keeps the REST routes' schema,
    which is the same model's."""
    components = openapi.setdefault("components", {}).setdefault("schemas", {})
    for name, schema in json_schemas().items():
        components.setdefault(name, schema)
    return openapi


PROTOCOL_MARKDOWN = f"""\
**Teleop WebSocket `{PATH}`.** OpenAPI describes no WebSockets: this socket's messages are JSON
objects whose schemas are in `components.schemas` (details and examples in the repository's
`docs/websocket.md`).

- **Auth**: `Authorization: Bearer TOKEN` on the handshake, or `?token=TOKEN` (browsers cannot set the
  header). Without a valid token the handshake is refused with HTTP 401. Any role may watch; commands need
  the operator role, and only the robot's lease holder may command: claim the robot and renew the lease with
  heartbeats over REST (`POST /api/v1/robots/{{robot_id}}/claim`, `.../heartbeat`); socket traffic does not renew it.
- **Client to server**: `{TeleopCommandIn.__name__}`, the body of `POST /api/v1/robots/{{robot_id}}/command`.
- **Server to client** (`{TeleopServerMessage.__name__}` is any of them): `{TeleopStateMessage.__name__}` every
  {STATE_PERIOD_S:g} s; one `{TeleopAcceptedMessage.__name__}` or `{TeleopErrorMessage.__name__}` answering each
  client message, in order. A refused message changes nothing and the socket stays open.
- **Close codes**: {CLOSE_UNKNOWN_ROBOT} after the 404 error for an unknown robot; 1000 when the client closes;
  1012 when the service shuts down.
"""
