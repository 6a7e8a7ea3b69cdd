"""ASGI middleware of ``lsgan serve``, outermost first: which hosts are served (:class:`HostCheck`), ``HEAD`` as
``GET`` without the body (:class:`HeadAsGet`), and bounded bodies (:class:`BodyLimit`). Each answers a refusal as the
API's JSON ``{"error": "one line"}``."""
from __future__ import annotations

import ipaddress
import socket

from fastapi.responses import JSONResponse

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def error(status: int, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status, headers=headers)


def served_hosts(host: str, extra: tuple[str, ...] = ()) -> frozenset[str] | None:
    """The names a server bound to ``host`` answers to (None: any, when ``extra`` holds ``*``): loopback's three
    names on loopback; on every interface (0.0.0.0, ::) those and this machine's name and addresses; else the
    bound address itself; plus ``extra`` (``--allow-host``)."""
    if "*" in extra:
        return None
    names = {name_of(h) for h in extra}
    bare = host.strip("[]")
    try:
        address = ipaddress.ip_address(bare)
    except ValueError:
        address = None
    if bare == "localhost" or (address is not None and (address.is_loopback or address.is_unspecified)):
        names.update(LOOPBACK_NAMES)
    if address is not None and address.is_unspecified:
        machine = socket.gethostname()
        names.update({machine.lower(), socket.getfqdn(machine).lower()})
        try:
            names.update(str(info[4][0]).split("%")[0] for info in socket.getaddrinfo(machine, None))
        except OSError:
            pass
    elif address is not None:
        names.add(str(address))
    else:
        names.add(name_of(bare))
    return frozenset(names)


def name_of(host: str) -> str:
    """The name in a Host header value or an address: lower case, no port, no brackets, no trailing dot."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else host[1:]
    if host.count(":") == 1:
        host = host.split(":")[0]
    return host.rstrip(".")


class HostCheck:
    """Only requests naming a served host (:func:`served_hosts`) reach the app: a web page that re-binds its own
    domain name to this machine's address (DNS rebinding) still sends its own name, and gets 400."""

    def __init__(self, app, allowed: frozenset[str] | None) -> None:
        self.app, self.allowed = app, allowed

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or self.allowed is None:
            return await self.app(scope, receive, send)
        values = [v for k, v in scope["headers"] if k == b"host"]
        if len(values) != 1:
            if values or scope.get("http_version") != "1.0":
                why = "several Host headers" if values else "no Host header (HTTP/1.1 requires one)"
                return await error(400, why)(scope, receive, send)
        elif name_of(values[0].decode("latin-1")) not in self.allowed:
            shown = ascii(values[0].decode("latin-1"))[1:-1][:80]
            return await error(400, f"host {shown!r} is not served here (this server answers to "
                                    f"{', '.join(sorted(self.allowed))}; add names with --allow-host)")(
                scope, receive, send)
        await self.app(scope, receive, send)


class HeadAsGet:
    """``HEAD`` is answered wherever ``GET`` is: the app sees a GET; uvicorn, whose scope still says HEAD, sends
    the head of the answer (its Content-Length included) and not the body."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http" and scope["method"] == "HEAD":
            scope = {**scope, "method": "GET"}
        await self.app(scope, receive, send)


class BodyLimit:
    """ASGI middleware: a body over ``max_bytes`` (by its Content-Length, or as it streams in) gets 413 before the
    app reads any of it; otherwise the app reads the buffered body."""

    def __init__(self, app, max_bytes: int) -> None:
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_nosniff(message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), (b"x-content-type-options", b"nosniff")]
            await send(message)

        too_big = f"request body over {self.max_bytes} bytes (the limit)"
        length = dict(scope["headers"]).get(b"content-length", b"").decode("latin-1")
        if length.isdigit() and int(length) > self.max_bytes:
            return await error(413, too_big)(scope, receive, send_nosniff)
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return None
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            more = message.get("more_body", False)
            if size > self.max_bytes:
                return await error(413, too_big)(scope, receive, send_nosniff)
        body, sent = b"".join(chunks), False

        async def replay():
            nonlocal sent
            if sent:
                return await receive()
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}

        await self.app(scope, replay, send_nosniff)


