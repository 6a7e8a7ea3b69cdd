"""ASGI middleware of ``lsgan serve``, outermost first: which hosts are served (:class:`HostCheck`), ``HEAD`` as
``GET`` without the body (:class:`HeadAsGet`), answers paced to the client (:class:`PacedBody`), and bounded request
bodies (:class:`BodyLimit`). Each answers a refusal as the API's JSON ``{"error": "one line"}``."""
from __future__ import annotations

import ipaddress
import re
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
    names = {name_of(h) or h.strip().lower() for h in extra}
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


_REG_NAME = re.compile(r"[a-z0-9._~!$&'()*+,;=%-]+")


def name_of(host: str) -> str | None:
    """The host in a Host header value or an address (RFC 3986's host [":" port]): lower case, without the port,
    the brackets of an IPv6 literal or a trailing dot; None when the value is not one (userinfo, a port that is not
    a number up to 65535, text after the brackets, an unclosed bracket, an empty name)."""
    value = host.strip().lower()
    if value.startswith("["):
        end = value.find("]")
        name, rest = (value[1:end], value[end + 1:]) if end > 0 else ("", "")
        try:
            ipaddress.IPv6Address(name)
        except ValueError:
            return None
    else:
        name, colon, port = value.partition(":")
        rest = colon + port
        if ":" in port or not name or not _REG_NAME.fullmatch(name):
            return None  # a bare IPv6 address too: a Host header writes it in brackets
    if rest and not (rest[0] == ":" and rest[1:].isdigit() and len(rest) <= 6 and int(rest[1:]) <= 65535):
        return None
    name = name.rstrip(".") if not name.endswith("..") else None
    return name or None


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
        elif (name_of(values[0].decode("latin-1")) or "") not in self.allowed:
            shown = ascii(values[0].decode("latin-1"))[1:-1][:80]
            return await error(400, f"host {shown!r} is not served here (this server answers to "
                                    f"{', '.join(sorted(self.allowed))}; add names with --allow-host)")(
                scope, receive, send)
        await self.app(scope, receive, send)


class PacedBody:
    """An answer's body goes out in pieces of PIECE bytes, each sent once the connection has taken the last
    (uvicorn waits while the transport's buffer is over its high-water mark): a client that reads slowly, or not at
    all, holds one piece in the server's buffers, not a copy of the whole answer."""

    PIECE = 65536

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def paced(message) -> None:
            body = message.get("body", b"")
            if message["type"] != "http.response.body" or len(body) <= self.PIECE:
                return await send(message)
            view, more = memoryview(body), message.get("more_body", False)
            for start in range(0, len(view), self.PIECE):
                last = start + self.PIECE >= len(view)
                await send({"type": "http.response.body", "body": bytes(view[start:start + self.PIECE]),
                            "more_body": more or not last})

        await self.app(scope, receive, paced)


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


