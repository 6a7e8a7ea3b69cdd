"""The HTTP API of ``lsgan serve`` (FastAPI): ``create_app(engines, limits)``.

Every answer other than 200 is JSON ``{"error": "<one line>"}``: 4xx for what the client sent, 503 when the server
is busy or a request timed out (with Retry-After), 500 only for a bug of ours (logged with its traceback, never
sent). Request bodies are bounded before anything reads them (:class:`BodyLimit`).
"""
from __future__ import annotations

import asyncio
import json
import logging
import secrets
import time
from concurrent.futures import ThreadPoolExecutor

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from lsgan import __version__
from lsgan.serve.batcher import Batcher, Busy
from lsgan.serve.checks import ApiError, parse_json, short, to_item
from lsgan.serve.engine import Engine, Item, Result
from lsgan.serve.files import FORMATS, download_name, export_bytes, static_bytes
from lsgan.serve.jsonfmt import joints_json
from lsgan.serve.limits import Limits
from lsgan.serve.middleware import BodyLimit, HeadAsGet, HostCheck, PacedBody, error
from lsgan.serve.schemas import ErrorOut, GenerateRequest, GenerateResponse, Health, Info
from lsgan.serve.store import MotionStore, Stored

log = logging.getLogger("lsgan.serve")
ERRORS = {code: {"model": ErrorOut} for code in (400, 401, 404, 413, 415, 422, 503)}
JSON_ROUND = 4  # decimals of the joints in JSON: 0.1 mm


def clip(text: str, limit: int = 80) -> str:
    """A client's string for a one-line message: non-ASCII and control characters escaped, cut to ``limit``."""
    text = ascii(text)[1:-1]
    return text if len(text) <= limit else text[:limit - 3] + "..."


def add_error_handlers(app: FastAPI) -> None:
    """Every error as ``{"error": one line}``."""

    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError):
        return error(exc.status, exc.message, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        if exc.status_code == 404:
            target = without_slash(request)
            if target is not None:  # a path, never the client's Host: the redirect stays on this server
                return error(308, f"no such route; it is {clip(target)}", {"Location": target})
            message = f"no such route: {request.method} {clip(request.url.path)}"
        elif exc.status_code == 405:
            message = f"method {request.method} not allowed on {clip(request.url.path)}"
        else:
            message = str(exc.detail).splitlines()[0] if exc.detail else "request refused"
        return error(exc.status_code, message, dict(exc.headers or {}))

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError):
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ())) or "request"
        return error(422, f"{where}: {first.get('msg', 'invalid')}")

    @app.exception_handler(Exception)
    async def bug(request: Request, exc: Exception):
        log.exception("internal error on %s %s", request.method, request.url.path)
        return error(500, f"internal error ({type(exc).__name__}); the server logged it")


def without_slash(request: Request) -> str | None:
    """The path and query of ``request`` without its trailing slashes, where a route answers that path."""
    from starlette.routing import Match

    path = request.url.path
    if len(path) < 2 or not path.endswith("/"):
        return None
    bare = path.rstrip("/") or "/"
    if not bare.startswith("/") or bare.startswith("//"):
        return None
    scope = {**request.scope, "path": bare}
    if not any(route.matches(scope)[0] == Match.FULL for route in request.app.router.routes):
        return None
    query = request.url.query
    return bare + (f"?{query}" if query else "")


def key_check(api_key: str):
    """A dependency: /v1 needs ``Authorization: Bearer KEY`` or ``X-API-Key: KEY``. Every key offered is
    compared (in constant time), so an empty or malformed header beside a correct one does not hide it; the two
    security schemes are declared in the OpenAPI schema, so /docs can send the key.

    A coroutine, though it awaits nothing: FastAPI runs a plain function dependency in a worker thread, a thread
    switch per request for a few dictionary lookups."""
    from fastapi import Security
    from fastapi.security import APIKeyHeader, HTTPBearer

    header = APIKeyHeader(name="X-API-Key", auto_error=False, description="the server's API key")
    bearer = HTTPBearer(auto_error=False, description="the server's API key as a bearer token")
    expected = api_key.encode("ascii")

    async def check(request: Request, _h=Security(header), _b=Security(bearer)) -> None:
        offered = [v.strip() for v in request.headers.getlist("x-api-key")]
        for auth in request.headers.getlist("authorization"):
            scheme, _, token = auth.strip().partition(" ")
            if scheme.lower() == "bearer":
                offered.append(token.strip())
        offered = [v for v in offered if v]
        if not offered:
            raise ApiError(401, "this server needs an API key: send Authorization: Bearer KEY (or X-API-Key: KEY)",
                           {"WWW-Authenticate": "Bearer"})
        matches = [secrets.compare_digest(v.encode("utf-8", "replace"), expected) for v in offered]
        if not any(matches):
            raise ApiError(401, "wrong API key", {"WWW-Authenticate": "Bearer"})
    return check


def info_of(engine: Engine, limits: Limits, auth: bool) -> dict:
    from lsgan.data.skeleton import JOINT_NAMES, KINEMATIC_CHAIN, PARENTS
    from lsgan.export.preview import CHAIN_COLOURS

    return {
        "condition": engine.condition, "actions": list(engine.actions), "fps": float(engine.fps),
        "max_frames": limits.max_frames, "default_frames": limits.default_frames, "min_frames": limits.min_frames,
        "limits": limits.as_dict(), "auth": auth,
        "control": None if engine.reach is None else {"steers": bool(engine.steers),
                                                      "max_speed_m_s": engine.reach["speed"]},
        "skeleton": {"names": list(JOINT_NAMES), "parents": list(PARENTS), "chains": [list(c) for c in KINEMATIC_CHAIN],
                     "chain_colours": ["#%02x%02x%02x" % c for c in CHAIN_COLOURS]},
    }


def create_app(engines: list[Engine], limits: Limits, *, api_key: str | None = None,
               hosts: frozenset[str] | None = None) -> FastAPI:
    """The API over one engine or several alike (passes side by side): the batcher and store start with the app
    and stop (draining) with it. ``hosts``: the Host names served (None: any; :func:`middleware.served_hosts`)."""
    from contextlib import asynccontextmanager

    engine = engines[0]  # what the API says of the model
    state: dict = {}

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        state["batcher"] = Batcher(engines, gather_ms=limits.gather_ms, max_batch=limits.max_batch,
                                   max_in_flight=limits.max_in_flight)
        state["store"] = MotionStore(limits.store_size)
        state["writer"] = ThreadPoolExecutor(2, thread_name_prefix="lsgan-answer")  # few threads to share the GIL
        yield
        await run_in_threadpool(state["batcher"].close)
        state["writer"].shutdown()

    app = FastAPI(title="lsgan", version=__version__, lifespan=lifespan, summary="Text and action to motion: "
                  "a GAN in a motion VAE's latent space. Errors are {\"error\": \"one line\"}.",
                  docs_url=None, redoc_url=None, redirect_slashes=False)
    app.add_middleware(BodyLimit, max_bytes=limits.max_body_bytes)
    app.add_middleware(PacedBody)
    app.add_middleware(HeadAsGet)
    app.add_middleware(HostCheck, allowed=hosts)
    add_error_handlers(app)
    add_docs_routes(app)
    v1 = APIRouter(prefix="/v1", dependencies=[Depends(key_check(api_key))] if api_key else [], responses=ERRORS)
    info = info_of(engine, limits, api_key is not None)
    add_page_routes(app)

    @app.get("/healthz", response_model=Health, tags=["server"])
    async def healthz():
        return {"status": "ok"}

    @v1.get("/info", response_model=Info, tags=["api"])
    async def get_info():
        """The model (condition, actions, frame bounds), the server's limits and the skeleton to draw."""
        return info

    @v1.post("/generate", response_model=GenerateResponse, tags=["api"],
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/json": {"schema": GenerateRequest.model_json_schema()}}}})
    async def generate(request: Request):
        """Motions for a prompt or an action; micro-batched with concurrent requests into one engine pass."""
        arrived = time.perf_counter()
        kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if kind != "application/json":
            raise ApiError(415, f"send the body as JSON (Content-Type: application/json), not {short(kind or 'none')}")
        item = to_item(parse_json(await request.body()), engine, limits, state["store"].joints)
        job, result = await _run(state["batcher"], item, limits.timeout_s)
        body = await asyncio.get_running_loop().run_in_executor(
            state["writer"], _respond, state["store"], item, result, engine.fps, 1e3 * (job.started_at - job.queued_at),
            arrived)
        return Response(body, media_type="application/json")

    @v1.get("/motions/{name}", tags=["api"], response_class=Response,
            responses={200: {"content": {t: {} for t in FORMATS.values()}, "description": "the file"}})
    async def download(name: str):
        """A stored motion as ``ID.glb``, ``ID.bvh`` or ``ID.npy``."""
        key, _, fmt = name.rpartition(".")
        if fmt not in FORMATS:
            raise ApiError(404, f"unknown format {short(fmt)}: ask for ID.glb, ID.bvh or ID.npy")
        motion = state["store"].get(key)
        if motion is None:
            raise ApiError(404, f"no motion {short(key)}: an unknown id, or one dropped from the store (it keeps the "
                                f"last {limits.store_size} motions)")
        data = await run_in_threadpool(export_bytes, motion, fmt)
        return Response(data, media_type=FORMATS[fmt], headers={
            "Content-Disposition": f'attachment; filename="{download_name(motion, key, fmt)}"'})

    app.include_router(v1)
    return app


async def _run(batcher: Batcher, item: Item, timeout_s: float):
    """(job, result) of ``item`` through the batcher; 503 when it is full or the answer takes over ``timeout_s``."""
    try:
        job = batcher.submit(item)
    except Busy as e:
        raise ApiError(503, str(e), {"Retry-After": str(e.retry_after)}) from None
    try:
        result = await asyncio.wait_for(asyncio.wrap_future(job.future), timeout_s)
    except (asyncio.TimeoutError, TimeoutError):
        raise ApiError(503, f"timed out after {timeout_s:g} s: the server is overloaded; retry shortly",
                       {"Retry-After": "2"}) from None
    except ValueError as e:  # the model refused the item (checks.to_item should have caught it)
        raise ApiError(422, str(e).splitlines()[0] if str(e) else "the model refused this request") from None
    finally:
        batcher.done(job)
    return job, result


def _respond(store: MotionStore, item: Item, result: Result, fps: float, queue_ms: float, arrived: float) -> bytes:
    """The JSON answer: each motion stored for download, its joints rounded to 0.1 mm (:mod:`jsonfmt`)."""
    motions = []
    for k, joints in enumerate(result.joints):
        key = store.add(Stored(joints=joints, fps=fps, title=item.text or item.action or "motion"))
        head = json.dumps({"id": key, "frames": int(len(joints)),
                           "urls": {fmt: f"/v1/motions/{key}.{fmt}" for fmt in FORMATS},
                           **({"control": result.control[k]} if result.control else {})}, separators=(",", ":"))
        motions.append(head[:-1].encode() + b',"joints":' + joints_json(joints, JSON_ROUND) + b"}")
    timings = {"queue": round(queue_ms, 3), **{k: round(v, 3) for k, v in result.timings_ms.items()},
               "total": round(1e3 * (time.perf_counter() - arrived), 3)}
    placement = None if item.placement is None else dict(zip(("yaw_rad", "x_m", "z_m"), item.placement))
    rest = json.dumps({"seed": item.seed, "fps": fps, "timings_ms": timings, "batch_size": result.batch_size,
                       **({"placement": placement} if placement else {})}, separators=(",", ":"))
    return b'{"motions":[' + b",".join(motions) + b"]," + rest[1:].encode()


def add_page_routes(app: FastAPI) -> None:
    """The page at / and its files at /static/NAME (only the files the package holds)."""

    @app.get("/", include_in_schema=False)
    async def page():
        found = static_bytes("index.html")
        if found is None:
            raise ApiError(404, "the page is not installed (lsgan/serve/static/index.html); the API is at /v1")
        return Response(found[0], media_type=found[1], headers={"Cache-Control": "no-cache"})

    @app.get("/static/{name}", include_in_schema=False)
    async def static(name: str):
        found = static_bytes(name)
        if found is None:
            raise ApiError(404, f"no page file {short(name)}")
        return Response(found[0], media_type=found[1], headers={"Cache-Control": "no-cache"})


def add_docs_routes(app: FastAPI) -> None:
    """/docs: Swagger UI from the files the installed fastapi-offline package ships (no network), or a one-line
    pointer to the schema where that package is missing."""
    from importlib.resources import files

    from fastapi.openapi.docs import get_swagger_ui_html

    try:
        assets_dir = files("fastapi_offline") / "static"
    except ModuleNotFoundError:
        assets_dir = None
    types = {"swagger-ui-bundle.js": "text/javascript", "swagger-ui.css": "text/css", "favicon.png": "image/png"}
    assets = {name: ((assets_dir / name).read_bytes(), kind) for name, kind in types.items()} if assets_dir else {}

    @app.get("/docs", include_in_schema=False)
    async def docs():
        if assets_dir is None:
            raise ApiError(404, "the docs page needs the fastapi-offline package (pip install 'lsgan[serve]'); the "
                                "schema is at /openapi.json, the API in docs/api.md")
        return get_swagger_ui_html(openapi_url="/openapi.json", title="lsgan API",
                                   swagger_js_url="/docs/swagger-ui-bundle.js", swagger_css_url="/docs/swagger-ui.css",
                                   swagger_favicon_url="/docs/favicon.png")

    @app.get("/docs/{name}", include_in_schema=False)
    async def docs_asset(name: str):
        if name not in assets:
            raise ApiError(404, f"no docs file {short(name)}")
        return Response(assets[name][0], media_type=assets[name][1], headers={"Cache-Control": "max-age=86400"})
