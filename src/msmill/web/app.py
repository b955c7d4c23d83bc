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

from msmill._version import __version__
from msmill.errors import MsmillInputError
from msmill.web.service import PredictionService, default_request

MAX_REQUEST_BYTES = 1_000_000
STATIC = Path(__file__).with_name("static")


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

    @app.get("/defaults")
    def defaults() -> dict[str, Any]:
        """The shipped UG2 example as a request body."""
        return default_request()

    @app.post("/predict")
    def predict(request: Annotated[dict[str, Any], Body(description="run-file fields (msmill.model.runfile) "
                                                                    "plus optional attachments")]) -> dict[str, Any]:
        """Predict the product of a run file given as JSON."""
        return svc.predict(request)

    return app
