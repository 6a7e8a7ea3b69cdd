"""``lsgan serve``: load the models once in each engine process (:mod:`lsgan.serve.worker`), then run the API
under uvicorn until SIGTERM or Ctrl-C.

Engine processes: by default one per usable core, at most :data:`MAX_WORKERS`, so that passes run side by side
on one thread each under load (:mod:`lsgan.serve.batcher`); one when the engine computes on a GPU.

SIGTERM stops accepting connections, lets the requests in flight finish (uvicorn's graceful shutdown), stops the
batcher's threads and the engine processes and returns normally, so the command exits 0. Ctrl-C does the same and
then exits 130, as every lsgan command does. A second signal does not cut the drain short (uvicorn would force the
exit on one); SIGKILL stops at once.
"""
from __future__ import annotations

import gc
import ipaddress
import logging
import os
import signal
import socket
import sys
from collections.abc import Callable

from lsgan.serve.engine import Engine, load_engine
from lsgan.serve.limits import Limits
from lsgan.serve.middleware import served_hosts
from lsgan.serve.worker import EngineProcess
from lsgan.threads import usable_cpus

MAX_WORKERS = 4  # engine processes by default: each holds its own copy of the models
FILE_MARGIN = 256  # open files beside the connections: models, pipes to the engines, logs
BACKLOG = 4096  # connections the kernel queues for accepting (Linux caps it at net.core.somaxconn): in a flood a new
# client waits behind them, about 13 us each (a lobby, lsgan.serve.protocol), and past them its SYN is dropped
MAX_KEY_CHARS = 1024  # an API key fits in a request head whatever --max-header-bytes (at least 1,024) allows


def is_loopback(host: str) -> bool:
    """Whether ``host`` only listens on this machine (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def listen(host: str, port: int) -> socket.socket:
    """A socket bound to ``host:port`` (port 0: a free one); a one-line OSError when that is not possible."""
    try:
        infos = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise OSError(f"{host}: not an address or host name this machine knows ({e.strerror})") from None
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)  # proto TCP: asyncio then sets TCP_NODELAY on each connection
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as e:
        sock.close()
        raise OSError(f"{host}:{port}: cannot listen there ({(e.strerror or str(e)).lower()})") from None
    sock.set_inheritable(True)
    return sock


def checked_key(api_key: str | None) -> str | None:
    """The API key as given, or a ValueError: a key is visible ASCII (33-126), which every client can send."""
    if api_key is None:
        return None
    if not api_key:
        raise ValueError("the API key is empty")
    if len(api_key) > MAX_KEY_CHARS:
        raise ValueError(f"the API key is {len(api_key):,} characters long: at most {MAX_KEY_CHARS} (a request's "
                         "headers are bounded, so a longer one could never be sent)")
    bad = next((c for c in api_key if not 33 <= ord(c) <= 126), None)
    if bad is not None:
        raise ValueError(f"the API key holds {ascii(bad)}: use visible ASCII characters only (no spaces), which "
                         "every HTTP client can send")
    return api_key


def read_key_file(path: str) -> str:
    """The API key in ``path``: its first line, without the line break."""
    try:
        with open(path, encoding="ascii", errors="strict") as fh:
            return fh.readline().rstrip("\r\n")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: the API key file is not ASCII") from None
    except OSError as e:
        raise OSError(f"{path}: cannot read the API key file ({(e.strerror or str(e)).lower()})") from None


def open_files_for(limits: Limits) -> None:
    """Raise the soft limit on open files towards the hard one so that ``max_connections`` fit with room for the
    models, pipes and log files (FILE_MARGIN); a ValueError naming both when they cannot."""
    try:
        import resource
    except ImportError:  # Windows: no such limit to raise
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = limits.max_connections + FILE_MARGIN
    if soft != resource.RLIM_INFINITY and soft < want:
        target = want if hard == resource.RLIM_INFINITY else min(want, hard)
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    if soft != resource.RLIM_INFINITY and soft < want:
        raise ValueError(f"--max-connections {limits.max_connections} needs {want} open files, and this process may "
                         f"open {soft} (ulimit -n): lower --max-connections or raise the limit")


def _draining_server(config):
    """uvicorn's server, except that a second signal does not cut the drain short (uvicorn forces the exit on a
    Ctrl-C after any signal, cancelling its lifespan task mid-await and logging that as a traceback): the requests in
    flight always finish, within the graceful-shutdown timeout; SIGKILL remains for an immediate stop."""
    import uvicorn

    class DrainingServer(uvicorn.Server):
        def handle_exit(self, sig: int, frame) -> None:
            self._captured_signals.append(sig)  # as uvicorn's: raised again once it has shut down
            self.should_exit = True

    return DrainingServer(config)


def serve(*, gan: str | None = None, vae: str | None = None, model: str | None = None, int8: bool = False,
          host: str = "127.0.0.1", port: int = 8000, api_key: str | None = None, limits: Limits | None = None,
          device: str = "auto", text_encoder_path: str | None = None, text_cache: int = 1024,
          workers: int | None = None, allow_hosts: tuple[str, ...] = (),
          say: Callable[[str], None] = lambda m: print(m, file=sys.stderr, flush=True)) -> None:
    """Serve ``--gan/--vae`` checkpoints or an ONNX ``--model`` folder on ``host:port`` until stopped, with
    ``workers`` engine processes (default: :func:`start_engines`'s), answering to the Host names of
    :func:`lsgan.serve.middleware.served_hosts` (``allow_hosts`` added)."""
    try:
        import fastapi  # noqa: F401 - checked before minutes of loading
        import uvicorn  # noqa: F401
    except ImportError as e:
        raise RuntimeError(f"lsgan serve needs FastAPI and uvicorn ({e.name} is missing): "
                           "pip install 'lsgan[serve]'") from None

    if not 0 <= port <= 65535:
        raise ValueError(f"port {port} is not a TCP port (0 to 65535)")
    api_key = checked_key(api_key)
    open_files_for(limits or Limits())
    hosts = served_hosts(host, allow_hosts)
    sock = listen(host, port)  # first: a port in use fails before minutes of loading
    try:
        engines = start_engines(dict(gan=gan, vae=vae, model=model, int8=int8, device=device,
                                     text_encoder_path=text_encoder_path, text_cache=text_cache), workers)
    except BaseException:
        sock.close()
        raise
    try:
        limits = (limits or Limits()).checked(engines[0].max_frames)
        _run(engines, limits, sock, host, api_key, hosts, say)
    finally:
        for engine in engines:
            engine.close()
        sock.close()


def start_engines(load_args: dict, workers: int | None = None) -> list[Engine]:
    """``workers`` engine processes, loaded one after another (default: one per usable core, at most
    :data:`MAX_WORKERS`, or only the first when it computes on a GPU). An ONNX engine's sessions get the cores
    divided among the processes. Where a child cannot be handed its pipes (``pass_fds``: POSIX only), one engine
    in this process."""
    if workers is not None and workers < 1:
        raise ValueError(f"--workers {workers}: at least one engine process is needed")
    if os.name != "posix":
        return [load_engine(**load_args)]
    count = workers or min(usable_cpus(), MAX_WORKERS)
    if load_args.get("model") and count > 1:
        load_args = {**load_args, "threads": max(1, usable_cpus() // count)}
    engines: list[Engine] = [EngineProcess(**load_args)]
    try:
        while len(engines) < count and (workers or engines[0].device == "cpu"):
            engines.append(EngineProcess(**load_args))
    except BaseException:
        for engine in engines:
            engine.close()
        raise
    return engines


def _run(engines: list[Engine], limits: Limits, sock: socket.socket, host: str, api_key: str | None,
         hosts: frozenset[str] | None, say: Callable[[str], None]) -> None:
    """uvicorn on ``sock`` over ``engines`` until SIGTERM or Ctrl-C, speaking bounded HTTP
    (:mod:`lsgan.serve.protocol`); the requests in flight finish first."""
    import uvicorn

    from lsgan.serve.app import create_app
    from lsgan.serve.protocol import protocol_class

    if not is_loopback(host):
        say(f"warning: listening on {host}: other machines can reach this server"
            + ("" if api_key else " and use it without a key (--api-key)"))
    port = sock.getsockname()[1]
    server = _draining_server(uvicorn.Config(create_app(engines, limits, api_key=api_key, hosts=hosts),
                                           http=protocol_class(limits), timeout_keep_alive=limits.keep_alive_s,
                                           log_level="warning", access_log=False, server_header=False,
                                           timeout_graceful_shutdown=limits.timeout_s + 5))
    gc.collect()
    gc.freeze()  # the app's objects stay out of every later collection (the child does so for the models)
    came: list[int] = []  # from before the line saying the server is ready

    def record(sig: int, frame) -> None:
        """A signal before uvicorn takes them (it would never stop) or one it raises again after draining (raised
        inside it, an exception becomes a traceback): noted, and the server told to stop."""
        came.append(sig)
        server.should_exit = True

    previous = {s: signal.signal(s, record) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        sock.listen(BACKLOG)  # from here connections wait in the backlog until uvicorn accepts them
        url = f"http://{f'[{host}]' if ':' in host else host}:{port}/"
        processes = f"{len(engines)} engine processes" if len(engines) > 1 else "one engine process"
        say(f"lsgan serve: {engines[0].describe()}, {processes}, loaded in {sum(e.load_s for e in engines):.1f} s; "
            f"{url} (API /v1, docs {url}docs); "
            f"{'API key required' if api_key else 'no API key'}; Ctrl-C or SIGTERM stops")
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        server.run(sockets=[sock])
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    say("lsgan serve: stopped")
    if signal.SIGINT in came:  # Ctrl-C: the program exits 130, as every command does after one
        signal.raise_signal(signal.SIGINT)
