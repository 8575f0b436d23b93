"""The client's errors. A refusal of the server carries its ``{"error": {"code", "message",
"field", "hint"}}`` as attributes, so that a notebook can act on it (``e.field``, ``e.hint``)."""

from __future__ import annotations


class ScnerfError(Exception):
    """Anything this client raises."""


class ConnectionFailed(ScnerfError):
    """The server did not answer (not running, wrong URL, network down)."""


class CaptureError(ScnerfError):
    """A capture folder that cannot be sent as it is (no files, larger than the server takes)."""


class ServerError(ScnerfError):
    """The server refused a request: its HTTP status and its own code, message, field and hint."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        field: str | None = None,
        hint: str | None = None,
        request_id: str | None = None,
    ):
        self.status, self.code, self.message = status, code, message
        self.field, self.hint, self.request_id = field, hint, request_id
        where = f" [field: {field}]" if field else ""
        super().__init__(f"the server refused the request ({status} {code}): {message}{where}")


class InvalidRequest(ServerError):
    """400, 413, 415, 422: what was sent is malformed, too large or not usable (``field`` says where)."""


class Unauthorized(ServerError):
    """401: no token or a wrong one (``Client(url, token=...)``)."""


class SceneNotFound(ServerError):
    """404 ``scene_not_found``: the scene expired, was evicted or deleted (hint ``reupload``)."""


class ModelNotFound(ServerError):
    """404 ``model_not_found``: the server serves no model of that name (``Client.models()``)."""


class ModelMismatch(ServerError):
    """409 ``model_mismatch``: the scene belongs to another model than the one named."""


class Overloaded(ServerError):
    """429 or 503 still answered after the client's retries (``retry_after`` seconds)."""

    retry_after: float | None = None


def server_error(
    status: int, body: bytes, request_id: str | None = None, retry_after: float | None = None
) -> ServerError:
    """The typed error of a non-2xx answer: the server's error body, or the start of any other body."""
    import json

    try:
        detail = json.loads(body)["error"]
        code, message = str(detail["code"]), str(detail["message"])
        field, hint = detail.get("field"), detail.get("hint")
    except (ValueError, KeyError, TypeError):
        code, message, field, hint = f"http_{status}", body[:200].decode(errors="replace"), None, None
    kind: type[ServerError] = ServerError
    if status == 401:
        kind = Unauthorized
    elif status == 404 and code == "scene_not_found":
        kind = SceneNotFound
    elif status == 404 and code == "model_not_found":
        kind = ModelNotFound
    elif status == 409 and code == "model_mismatch":
        kind = ModelMismatch
    elif status in (429, 503):
        kind = Overloaded
    elif status in (400, 413, 415, 422):
        kind = InvalidRequest
    error = kind(status, code, message, field, hint, request_id)
    if isinstance(error, Overloaded):
        error.retry_after = retry_after
    return error
