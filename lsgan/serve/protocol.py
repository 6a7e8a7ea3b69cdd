"""Bounded HTTP/1.x for ``lsgan serve``: uvicorn's httptools protocol with the limits it lacks.

uvicorn gives an idle keep-alive timeout (``timeout_keep_alive``, used as is) but no bound on a request's head,
no deadline for receiving it or its body, and no cap on open connections; httptools concatenates a header's
pieces as they arrive, so one 64 MB header costs seconds of the event loop. :func:`protocol_class` adds, per
connection (each bound is a :class:`lsgan.serve.limits.Limits` field and a command-line option):

- the head (request line and headers) is fed to the parser only up to ``max_header_bytes``: past it, 431;
  a request line over ``max_line_bytes``: 414; more than ``max_headers`` headers: 431;
- a connection's first head must arrive within ``header_timeout_s`` of its opening, a later one within that of
  its first byte (or of blank lines sent between requests), its body within ``body_timeout_s`` of the head: else 408; a client that stops taking an answer is closed when it
  has taken nothing more for ``body_timeout_s``;
- only HTTP/1.0 and 1.1: others (HTTP/0.9-style request lines, ``HTTP/2.0``) get 505; a malformed request 400;
- until its first byte a connection is a :class:`Lobby`, a few fields and a shared deadline, not a full protocol:
  a flood of silent connections costs the event loop a fifth as much per connection;
- at most ``max_connections`` open: a new connection over it closes the connection that has waited longest
  without a request being answered (idle keep-alive, a head or a body still arriving; a refused one lingering
  goes first); when every one is being answered, the newcomer gets a quick 503. So idle and slow clients cannot
  lock out a well-behaved one.

Every refusal is the API's JSON ``{"error": "one line"}`` with ``Connection: close``, and nothing is logged for a
client's misbehaviour. At shutdown, connections whose request has not fully arrived are closed at once (503)
rather than waited for; requests whose body is in are answered (uvicorn's graceful shutdown).
"""
from __future__ import annotations

import asyncio
import http
import json
from collections import OrderedDict, deque

import httptools
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from lsgan.serve.limits import Limits

LINGER_S = 2.0  # after a refusal mid-request, how long what the client still sends is read and thrown away


class Refusal(Exception):
    """Raised in a parser callback to stop parsing and answer ``status`` with ``message``."""

    def __init__(self, status: int, message: str, retry_after: int | None = None) -> None:
        super().__init__(message)
        self.status, self.message, self.retry_after = status, message, retry_after


def refusal_bytes(status: int, message: str, retry_after: int | None = None,
                  default_headers: list[tuple[bytes, bytes]] = ()) -> bytes:
    """A whole HTTP/1.1 response: JSON ``{"error": message}``, ``Connection: close``."""
    body = json.dumps({"error": message}).encode()
    head = [f"HTTP/1.1 {status} {http.HTTPStatus(status).phrase}".encode()]
    head += [name + b": " + value for name, value in default_headers]
    head += [b"content-type: application/json", b"content-length: %d" % len(body), b"connection: close",
             b"x-content-type-options: nosniff"]
    if retry_after is not None:
        head.append(b"retry-after: %d" % retry_after)
    return b"\r\n".join(head) + b"\r\n\r\n" + body


def parser_refusal(error: Exception) -> Refusal:
    """The refusal for an httptools error: ours when a callback raised one, else what the parser says, in one line."""
    if isinstance(error.__context__, Refusal):
        return error.__context__
    reason = (str(error).splitlines() or [""])[0] or type(error).__name__
    if "HTTP version" in reason or "PRI" in reason:
        return Refusal(505, "this HTTP version is not served here: send HTTP/1.1")
    if isinstance(error.__context__, Exception) and str(error.__context__):
        reason = str(error.__context__).splitlines()[0]
    return Refusal(400, f"malformed HTTP request: {reason}")


class Connections:
    """The server's open connections, those waiting without a request being answered in the order they began to
    wait (the first to evict)."""

    def __init__(self) -> None:
        self.open: set = set()
        self.waiting: OrderedDict = OrderedDict()

    def admit(self, conn, cap: int) -> bool:
        """Count ``conn`` in, closing the longest-waiting connection when ``cap`` are open; False (``conn`` not
        counted) when all of them are being answered."""
        if len(self.open) >= cap:
            if not self.waiting:
                return False
            oldest, _ = self.waiting.popitem(last=False)
            oldest.drop()
        self.open.add(conn)
        self.wait(conn)
        return True

    def wait(self, conn) -> None:
        self.waiting.pop(conn, None)
        self.waiting[conn] = None

    def busy(self, conn) -> None:
        self.waiting.pop(conn, None)

    def first_out(self, conn) -> None:
        """``conn`` is done with (refused, lingering): the first to close when room is needed."""
        self.waiting[conn] = None
        self.waiting.move_to_end(conn, last=False)

    def gone(self, conn) -> None:
        self.open.discard(conn)
        self.waiting.pop(conn, None)


class BoundedProtocol(HttpToolsProtocol):
    """HttpToolsProtocol with the module's bounds; ``limits`` and ``connections`` are set by :func:`protocol_class`."""

    limits: Limits
    connections_of_server: Connections
    opened_at: float | None = None  # when the connection opened, if before this protocol took it over (a Lobby's)

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.head_bytes, self.in_head, self.closed, self.timer, self.header_count = 0, True, False, None, 0
        self.head_start, self.requests = self.opened_at or self.loop.time(), 0  # the first head's deadline counts
        # from the connection's opening, a later one's from its first byte
        self.running = None  # the request being answered (uvicorn's ``cycle`` is the newest parsed one)
        self.begun = False  # a request has begun to arrive and is not complete
        self.stall = None  # the deadline of a client that has stopped reading an answer
        self.body_bytes = 0  # bytes fed to the parser since the head (body, chunk framing, trailers)
        if not self.connections_of_server.admit(self, self.limits.max_connections):
            self.refuse(Refusal(503, f"over {self.limits.max_connections} open connections (the limit); retry "
                                     "shortly", retry_after=1))
            return
        self.arm_head()

    def connection_lost(self, exc) -> None:
        self.connections_of_server.gone(self)
        self.disarm()
        if self.stall is not None:
            self.stall.cancel()
        self.closed = True
        # uvicorn marks only the newest parsed request as disconnected: one being answered from a pipeline, or
        # waiting in it, would write to the closed transport (uvloop raises). Every one of them is marked.
        for cycle in {id(c): c for c in (self.running, *(c for c, _ in self.pipeline)) if c is not None}.values():
            if not cycle.response_complete:
                cycle.disconnected = True
                cycle.message_event.set()
        self.pipeline.clear()
        super().connection_lost(exc)

    def _start_asgi_task(self, cycle, app) -> None:
        self.running = cycle
        super()._start_asgi_task(cycle, app)

    # --- deadlines ------------------------------------------------------------------------------------------------
    def arm(self, seconds: float, what: str) -> None:
        self.disarm()
        self.timer = self.loop.call_later(seconds, self.expire, seconds, what)

    def arm_head(self) -> None:
        """The head's deadline: ``header_timeout_s`` after ``head_start``."""
        limit = self.limits.header_timeout_s
        self.disarm()
        self.timer = self.loop.call_at(self.head_start + limit, self.expire, limit, "request headers")

    def disarm(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None

    def expire(self, seconds: float, what: str) -> None:
        self.timer = None
        self.refuse(Refusal(408, f"{what} not received within {seconds:g} s (the limit)"))

    def drop(self) -> None:
        """Close at once, without a word and discarding what is unsent (evicted while waiting, or stalled while
        taking an answer): the socket, its buffers and the answer's task are freed now, not when a client that does
        not read would have taken the rest."""
        self.connections_of_server.gone(self)
        self.closed = True
        self.disarm()
        self.transport.abort()

    def refuse(self, refusal: Refusal) -> None:
        """Answer ``refusal`` and close; only a line on the wire that no response has started on. A client that may
        still be sending (a head or body cut short) gets a lingering close: what it sends for up to LINGER_S more is
        read and discarded, so that closing does not reset the connection before it has read the answer."""
        if self.closed:
            return
        self.closed = True
        self.disarm()
        answering = any(c is not None and c.response_started and not c.response_complete
                        for c in (self.running, self.cycle))
        if self.cycle is not None and not self.cycle.response_complete:
            self.cycle.keep_alive = False
        if self.transport.is_closing():
            return
        if not answering:
            self.transport.write(refusal_bytes(refusal.status, refusal.message, refusal.retry_after,
                                               self.server_state.default_headers))
        if self.begun and self.transport.can_write_eof():
            self.connections_of_server.first_out(self)
            self.transport.write_eof()
            self.timer = self.loop.call_later(LINGER_S, self.transport.abort)
        else:
            self.transport.close()

    # --- feeding the parser ---------------------------------------------------------------------------------------
    def data_received(self, data: bytes) -> None:
        self._unset_keepalive_if_required()
        if self.closed:
            return  # refused: discarded while the connection lingers
        view = memoryview(data)
        try:
            while view and not self.closed:
                if not self.in_head:
                    self.body_bytes += len(view)
                    if self.body_bytes > self.limits.max_body_bytes + self.limits.max_header_bytes:
                        raise Refusal(413, f"request body over {self.limits.max_body_bytes} bytes (the limit; chunk "
                                           "framing and trailers count too)")
                    self.parser.feed_data(bytes(view))
                    break
                room = self.limits.max_header_bytes - self.head_bytes
                if room <= 0:
                    raise Refusal(431, f"request head over {self.limits.max_header_bytes} bytes (the limit)")
                part, view = view[:room], view[room:]
                self.head_bytes += len(part)
                self.parser.feed_data(bytes(part))
        except Refusal as r:
            self.refuse(r)
        except httptools.HttpParserUpgrade:
            pass  # no protocol upgrades here: the request is answered as a plain one
        except httptools.HttpParserError as e:
            self.refuse(parser_refusal(e))
            return
        if not self.closed and not self.begun and self.timer is None and (
                self.cycle is None or self.cycle.response_complete):
            # bytes that began no request (blank lines between requests) ended the keep-alive wait: what follows
            # is a head, with its deadline
            self.head_start = self.loop.time()
            self.arm_head()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.in_head, self.begun, self.header_count = True, True, 0
        if self.requests:
            self.head_start = self.loop.time()
        self.requests += 1
        self.connections_of_server.wait(self)
        self.arm_head()

    def on_url(self, url: bytes) -> None:
        super().on_url(url)
        if len(self.url) > self.limits.max_line_bytes:
            raise Refusal(414, f"request target over {self.limits.max_line_bytes} bytes (the limit)")

    def on_header(self, name: bytes, value: bytes) -> None:
        self.header_count += 1
        if self.header_count > self.limits.max_headers:
            raise Refusal(431, f"more than {self.limits.max_headers} request headers (the limit)")
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        version = self.parser.get_http_version()
        if version not in ("1.0", "1.1"):
            raise Refusal(505, f"HTTP/{version} is not served here: send HTTP/1.1")
        method = self.parser.get_method()
        if method == b"CONNECT" or not self.url.startswith((b"/", b"*")):
            raise Refusal(400, "request target must be a path (this is not a proxy: no CONNECT, no absolute URLs)")
        upgrade = self.parser.should_upgrade()
        if upgrade and any(k in (b"content-length", b"transfer-encoding") and v.strip() not in (b"", b"0")
                           for k, v in self.headers):
            raise Refusal(400, "protocol upgrades are not served here, and the Upgrade header hides this request's "
                               "body: send it without Upgrade (HTTP/1.1)")
        self.in_head, self.body_bytes = False, 0  # still evictable: the client owes the body
        self.arm(self.limits.body_timeout_s, "request body")
        super().on_headers_complete()
        if upgrade and self.cycle is not None:  # the parser stops here: nothing after this request is read
            self.cycle.keep_alive = False

    def on_message_complete(self) -> None:
        self.disarm()
        self.connections_of_server.busy(self)  # the request is in: being answered
        self.in_head, self.head_bytes, self.begun = True, 0, False  # next: the next request's head
        super().on_message_complete()

    def on_response_complete(self) -> None:
        if not self.closed and not self.pipeline:  # else the next pipelined request is answered now
            self.connections_of_server.wait(self)
        super().on_response_complete()

    def pause_writing(self) -> None:
        """The answer waits for the client to take it: while it takes some within every ``body_timeout_s``, it may
        go on; one that has taken nothing for that long is closed."""
        super().pause_writing()
        if self.stall is None:
            self.check_stall(self.transport.get_write_buffer_size())

    def check_stall(self, before: int) -> None:
        left = self.transport.get_write_buffer_size()
        if self.stall is not None and left >= before:
            self.stall = None
            self.drop()
        else:
            self.stall = self.loop.call_later(self.limits.body_timeout_s, self.check_stall, left)

    def resume_writing(self) -> None:
        super().resume_writing()
        if self.stall is not None:
            self.stall.cancel()
            self.stall = None

    def shutdown(self) -> None:
        """Server shutdown: a request still arriving is refused now; one that has arrived is answered first."""
        if self.begun:  # its head or its body is arriving
            self.refuse(Refusal(503, "the server is shutting down", retry_after=2))
        elif self.flow is not None and self.flow.write_paused:  # the client is not taking its answer
            self.drop()
        else:
            super().shutdown()


class Deadlines:
    """Deadlines that all fall the same time after they are set, so they expire in the order they were set: one
    timer serves them all (a timer each would cost a flood of silent connections a third more time)."""

    def __init__(self, seconds: float) -> None:
        self.seconds, self.entries, self.timer, self.compact_at = seconds, deque(), None, 1024

    def add(self, item, loop: asyncio.AbstractEventLoop) -> float:
        """``item.expire()`` is called ``seconds`` from now (it checks itself whether that still matters, by
        ``item.closed``); the deadline. The entries of closed items are dropped whenever they are over half of
        all, so memory follows the items still open, not how many came and went."""
        if len(self.entries) >= self.compact_at:
            self.entries = deque(e for e in self.entries if not e[1].closed)
            self.compact_at = max(1024, 2 * len(self.entries))
        deadline = loop.time() + self.seconds
        self.entries.append((deadline, item))
        if self.timer is None:
            self.timer = loop.call_at(self.entries[0][0], self.fire, loop)
        return deadline

    def fire(self, loop: asyncio.AbstractEventLoop) -> None:
        self.timer, now = None, loop.time()
        while self.entries and self.entries[0][0] <= now:
            self.entries.popleft()[1].expire()
        if self.entries:
            self.timer = loop.call_at(self.entries[0][0], self.fire, loop)


class Lobby(asyncio.Protocol):
    """A connection until its first byte arrives: counted, timed and evictable like any other, with none of the
    HTTP machinery, which :meth:`data_received` builds then (a :class:`BoundedProtocol` takes the transport over).
    A silent connection costs the event loop about 13 us instead of 60 us (2-core VM, uvloop), so in a flood of
    them a well-behaved client, queued behind them for accepting, is reached about four times sooner."""

    __slots__ = ("uvicorn_args", "server_state", "transport", "closed", "deadline")
    limits: Limits
    connections_of_server: Connections
    deadlines: Deadlines
    protocol: type[BoundedProtocol]

    def __init__(self, **uvicorn_args) -> None:  # config, server_state, app_state: what the protocol will need
        self.uvicorn_args = uvicorn_args
        self.server_state = uvicorn_args["server_state"]

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport, self.closed = transport, False
        self.server_state.connections.add(self)
        if not self.connections_of_server.admit(self, self.limits.max_connections):
            self.refuse(Refusal(503, f"over {self.limits.max_connections} open connections (the limit); retry "
                                     "shortly", retry_after=1))
            return
        self.deadline = self.deadlines.add(self, asyncio.get_running_loop())

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        transport, protocol = self.transport, self.protocol(**self.uvicorn_args)
        protocol.opened_at = self.deadline - self.limits.header_timeout_s
        self.leave()
        transport.set_protocol(protocol)
        protocol.connection_made(transport)
        protocol.data_received(data)

    def expire(self) -> None:
        if not self.closed:
            self.refuse(Refusal(408, f"request headers not received within {self.limits.header_timeout_s:g} s "
                                     "(the limit)"))

    def leave(self) -> None:
        """Out of the lobby: no longer counted here, and what it held is freed while its deadline waits."""
        if not self.closed:
            self.closed = True
            self.connections_of_server.gone(self)
            self.server_state.connections.discard(self)
            self.transport = self.uvicorn_args = self.server_state = None

    def connection_lost(self, exc) -> None:
        self.leave()

    def drop(self) -> None:
        """Evicted, or the server is shutting down: closed at once (nothing has arrived, so nothing is owed)."""
        transport = self.transport
        self.leave()
        transport.abort()

    shutdown = drop

    def refuse(self, refusal: Refusal) -> None:
        transport, headers = self.transport, self.server_state.default_headers
        self.leave()
        transport.write(refusal_bytes(refusal.status, refusal.message, refusal.retry_after, headers))
        transport.close()


def protocol_class(limits: Limits) -> type[Lobby]:
    """The protocol factory for one server: a :class:`Lobby` that hands over to a :class:`BoundedProtocol`, both
    with the server's limits and its own connection registry."""
    shared = {"limits": limits, "connections_of_server": Connections()}
    protocol = type("LsganHttpProtocol", (BoundedProtocol,), shared)
    return type("LsganLobby", (Lobby,), {**shared, "protocol": protocol, "deadlines": Deadlines(
        limits.header_timeout_s), "__slots__": ()})
