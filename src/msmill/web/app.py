"""The local web app and HTTP JSON API of ``msmill serve`` (FastAPI).

Endpoints (OpenAPI description at ``/openapi.json``, interactive at ``/docs``):

``GET /``
    the what-if page (``static/index.html``: plain HTML and JavaScript, no
    external assets, so it works on a machine without internet).
``GET /health``
    ``{"status": "ok", "version": ...}``.
``GET /ores``
    the ore library: name, A, b, L_ref and whether L_ref is calibrated.
``GET /defaults``
    the shipped UG2 example as a request body.
``POST /predict``
    a run file as JSON (plus optional ``attachments``, see
    :mod:`msmill.web.service`) -> summary, PSD table, per-stage table, time
    series, warnings, notes and the reproducing run file. Bad input: status
    422 with ``{"detail": {"field", "value", "allowed", "message"}}``.

Requests larger than :data:`MAX_REQUEST_BYTES` are refused with status 413
(FastAPI's body-size limit) without being read whole.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from fastapi import Body, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from msmill._version import __version__
from msmill.errors import MsmillInputError
from msmill.web.service import PredictionService, default_request

MAX_REQUEST_BYTES = 1_000_000
STATIC = Path(__file__).with_name("static")


class ErrorDetail(BaseModel):
    """One bad input: the field, the value given and what is allowed (``msmill.errors.MsmillInputError``)."""

    field: str
    value: str
    allowed: str
    message: str


class ErrorBody(BaseModel):
    """The body of every 422 answer of the API."""

    detail: ErrorDetail


_ERRORS = {422: {"model": ErrorBody, "description": "Bad input: the field, the value given and what is allowed"}}


def _request_schema() -> tuple[dict[str, Any], dict[str, Any]]:
    """JSON schema of a ``POST /predict`` body (a run file's fields plus ``attachments``) and its definitions."""
    from msmill.model.runfile import RunFile

    sch = RunFile.model_json_schema(ref_template="#/components/schemas/{model}")
    defs = sch.pop("$defs", {})
    props = {k: v for k, v in sch.get("properties", {}).items() if k not in ("base_dir", "name")}
    props["attachments"] = {
        "type": "object", "description": "file contents by kind: feed_csv (size_mm, passing_pct), ore_toml, "
        "stage_parameters_json, machine_toml (the run file's sections then point at them)",
        "additionalProperties": {"type": "string"}}
    body = {"type": "object", "title": "PredictRequest", "properties": props, "required": sch.get("required", []),
            "description": "A run file (msmill.model.runfile) as JSON, with optional attachments."}
    return body, defs


def _error(exc: MsmillInputError) -> JSONResponse:
    detail = {"field": exc.field, "value": str(exc.value), "allowed": exc.allowed, "message": str(exc)}
    return JSONResponse({"detail": detail}, status_code=422)


def _local_docs(app: FastAPI) -> None:
    """Swagger UI at ``/docs`` from files shipped with the install (``fastapi-offline``'s copy of Swagger UI,
    which reads OpenAPI 3.1), not from a CDN: the page renders with the network off."""
    from importlib import resources

    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.staticfiles import StaticFiles

    assets = str(resources.files("fastapi_offline") / "static")
    app.mount("/docs-assets", StaticFiles(directory=assets), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def docs() -> Any:
        return get_swagger_ui_html(openapi_url=app.openapi_url or "/openapi.json", title="msmill API",
                                   swagger_js_url="/docs-assets/swagger-ui-bundle.js",
                                   swagger_css_url="/docs-assets/swagger-ui.css",
                                   swagger_favicon_url="/docs-assets/favicon.png")


def create_app(service: PredictionService | None = None, max_request_bytes: int = MAX_REQUEST_BYTES) -> FastAPI:
    """The FastAPI application (one :class:`PredictionService` with its mill cache)."""
    svc = service or PredictionService()
    app = FastAPI(title="msmill", version=__version__, max_body_size=max_request_bytes, docs_url=None,
                  redoc_url=None, description="What-if predictions of a multi-shaft vertical impact mill.")
    _local_docs(app)

    @app.exception_handler(MsmillInputError)
    async def _bad_input(request: Request, exc: MsmillInputError) -> JSONResponse:
        return _error(exc)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 400:  # a body that cannot be parsed at all (not UTF-8): the API's own error body
            return _error(MsmillInputError("request", "an unreadable body", "a JSON object in UTF-8"))
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _bad_json(request: Request, exc: RequestValidationError) -> JSONResponse:
        err = exc.errors()[0] if exc.errors() else {}
        if err.get("type") == "json_invalid":
            pos = err.get("loc", ("body", "?"))[-1]
            return _error(MsmillInputError("request", f"malformed JSON at character {pos}", "a JSON object"))
        loc = ".".join(str(p) for p in err.get("loc", ()) if p not in ("body", "request"))
        field = f"request.{loc}" if loc else "request"
        return _error(MsmillInputError(field, err.get("input", ""), err.get("msg", "valid JSON")))

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html")

    @app.get("/health")
    def health() -> dict[str, str]:
        """Liveness and version."""
        return {"status": "ok", "version": __version__}

    @app.get("/ores")
    def ores() -> list[dict[str, Any]]:
        """The ore library."""
        from msmill.ore import get_ore, list_ores

        out = []
        for name in list_ores():
            ore = get_ore(name)
            out.append({"name": ore.name, "A_pct": ore.A_pct, "b_t_per_kwh": ore.b_t_per_kwh, "l_ref_mm": ore.l_ref_mm,
                        "l_ref_calibrated": not ore.l_ref_is_default})
        return out

    @app.get("/rotation-senses")
    def rotation_senses() -> list[dict[str, Any]]:
        """The rotation-sense configurations (``[machine] rotation_sense``) and whether each has a shipped surrogate."""
        from msmill.machine import DEFAULT_ROTATION_SENSE
        from msmill.machine import rotation_senses as senses
        from msmill.model.providers import sense_surrogate_path

        return [{"name": s, "default": s == DEFAULT_ROTATION_SENSE, "surrogate_shipped": sense_surrogate_path(s) is not None}
                for s in senses()]

    @app.get("/defaults")
    def defaults() -> dict[str, Any]:
        """The shipped UG2 example as a request body."""
        return default_request()

    body_schema, defs = _request_schema()

    @app.post("/predict", responses=_ERRORS, openapi_extra={"requestBody": {
        "required": True, "content": {"application/json": {"schema": body_schema}}}})
    def predict(request: Annotated[dict[str, Any], Body(description="run-file fields (msmill.model.runfile) "
                                                                    "plus optional attachments")]) -> dict[str, Any]:
        """Predict the product of a run file given as JSON."""
        return svc.predict(request)

    plain_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        """FastAPI's document plus the run file's definitions the request schema refers to."""
        if app.openapi_schema is None:
            doc = plain_openapi()
            doc.setdefault("components", {}).setdefault("schemas", {}).update(defs)
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app
