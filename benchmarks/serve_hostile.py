"""``lsgan serve`` under hostile clients: how fast a well-behaved client's /healthz is answered meanwhile.

Starts a real server (benchmarks/serve.py's: 127.0.0.1, a free port, ``--gan/--vae`` or demo-size models made in
seconds) with its default limits, then for each scenario measures ``--probes`` GET /healthz, each on a fresh
connection, one after another (latency: connect to last byte), while the attack runs:

- ``baseline``: no attack (measured first and last; the ratio column divides by the first);
- ``64MB-header``: one client streams a 64 MB header as fast as loopback takes it, again as soon as it is refused;
- ``idle-20000``: 20,000 connections opened at once and left silent (two attacker processes of 10,000, so that
  each stays under the open-file limit);
- ``reconnect-flood``: the same, each reopened as soon as the server closes it;
- ``slow-500``: 500 clients sending a request head a byte every 0.5 s (slowloris) and 500 more sending a body
  that way, reopened as the server closes them.

Reported per scenario: probes answered 200, p50/p99/max ms, max over the baseline's p50, and what the attackers
saw (answers by status, connections the server closed). The 1-minute load average is printed before and after.

    python benchmarks/serve_hostile.py --gan runs/bandai-gan --vae runs/bandai-vae [--probes 200] [--seconds 8]
        [--attacker-nice 19] [--only idle-20000 ...]
"""
from __future__ import annotations

import argparse
import http.client
import json
import multiprocessing
import os
import platform
import selectors
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path

from serve import Server, demo_size_models  # benchmarks/serve.py

NICE = 0  # --attacker-nice: the idle attackers' niceness (a remote attacker spends none of the server's CPU)


def probe(port: int) -> tuple[int, float]:
    start = time.perf_counter()
    try:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/healthz")
        resp = conn.getresponse()
        resp.read()
        conn.close()
        return resp.status, (time.perf_counter() - start) * 1000
    except OSError:
        return 0, (time.perf_counter() - start) * 1000


def probes(port: int, count: int, gap_s: float) -> dict:
    got = [probe(port) for _ in range(count) if time.sleep(gap_s) is None]
    ms = sorted(t for s, t in got if s == 200)
    return {"ok": len(ms), "sent": count, "p50": statistics.median(ms) if ms else None,
            "p99": ms[min(len(ms) - 1, int(0.99 * len(ms)))] if ms else None, "max": ms[-1] if ms else None}


def big_header(port: int, stop: threading.Event, seen: dict) -> None:
    """Stream a 64 MB header, again and again."""
    chunk = b"a" * (1 << 20)
    while not stop.is_set():
        s = socket.create_connection(("127.0.0.1", port), timeout=10)
        try:
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-Big: ")
            for _ in range(64):
                s.sendall(chunk)
            s.sendall(b"\r\n\r\n")
            answer = s.recv(64)
        except OSError:
            answer = b"closed"
        seen[answer[:12].decode("latin-1")] = seen.get(answer[:12].decode("latin-1"), 0) + 1
        s.close()


def hold_idle(port: int, count: int, seconds: float, reopen: bool, queue) -> None:
    """An attacker process: ``count`` silent connections, held; with ``reopen`` each is reopened as soon as the
    server closes it (a connection flood)."""
    import resource

    if NICE:
        os.nice(NICE)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    sel = selectors.DefaultSelector()
    opened = closed = failed = 0

    def open_one() -> None:
        nonlocal opened, failed
        s = socket.socket()
        s.setblocking(False)
        try:
            s.connect_ex(("127.0.0.1", port))
            sel.register(s, selectors.EVENT_READ)
            opened += 1
        except OSError:
            failed += 1
            s.close()

    for _ in range(count):
        open_one()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for key, _ in sel.select(0.05):
            sel.unregister(key.fileobj)
            key.fileobj.close()
            closed += 1
            if reopen:
                open_one()
    queue.put({"opened": opened, "closed_by_server": closed, "failed": failed})


def slow_clients(port: int, count: int, stop: threading.Event, seen: dict) -> None:
    """``count`` heads and ``count`` bodies trickling in a byte every 0.5 s; reopened when closed."""
    head = b"GET /healthz HTTP/1.1\r\nHost: localhost\r\nX-A: " + b"b" * 200
    body = b"POST /v1/generate HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\nContent-Length: 900\r\n\r\n"

    def start(kind: str):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.setblocking(False)
        s.send(body if kind == "body" else head)
        return [s, kind, 0]

    conns = [start("head") for _ in range(count)] + [start("body") for _ in range(count)]
    while not stop.is_set():
        for c in conns:
            try:
                c[0].send(b"x")
                c[2] += 1
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                try:
                    answer = c[0].recv(64)
                except OSError:
                    answer = b""
                key = answer[9:12].decode("latin-1") or "closed"
                seen[key] = seen.get(key, 0) + 1
                c[0].close()
                c[:] = start(c[1])
        stop.wait(0.5)
    for c in conns:
        c[0].close()


def scenario(name: str, port: int, args, seen: dict) -> dict:
    out = {"scenario": name, **probes(port, args.probes, args.seconds / args.probes)}
    out["attackers"] = dict(seen)
    print(json.dumps(out), flush=True)
    return out


SCENARIOS = ("64MB-header", "idle-20000", "reconnect-flood", "slow-500")


def run(port: int, args) -> list[dict]:
    rows = [scenario("baseline", port, args, {})]
    if "64MB-header" in args.only:
        stop, seen = threading.Event(), {}
        t = threading.Thread(target=big_header, args=(port, stop, seen), daemon=True)
        t.start()
        time.sleep(0.5)
        rows.append(scenario("64MB-header", port, args, seen))
        stop.set()
        t.join(30)

    for name, reopen in (("idle-20000", False), ("reconnect-flood", True)):
        if name not in args.only:
            continue
        queue = multiprocessing.Queue()
        attackers = [multiprocessing.Process(target=hold_idle, args=(port, 10000, args.seconds + 4, reopen, queue))
                     for _ in range(2)]
        for a in attackers:
            a.start()
        time.sleep(1)  # the connections are opening
        row = scenario(name, port, args, {})
        for a in attackers:
            a.join(60)
        row["attackers"] = [queue.get(timeout=10) for _ in attackers]
        print(json.dumps(row["attackers"]), flush=True)
        rows.append(row)

    if "slow-500" in args.only:
        stop, seen = threading.Event(), {}
        t = threading.Thread(target=slow_clients, args=(port, 500, stop, seen), daemon=True)
        t.start()
        time.sleep(2)
        rows.append(scenario("slow-500", port, args, seen))
        stop.set()
        t.join(30)
    rows.append(scenario("baseline-after", port, args, {}))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gan")
    ap.add_argument("--vae")
    ap.add_argument("--probes", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=8.0, help="per scenario, spread over its probes")
    ap.add_argument("--attacker-nice", type=int, default=0,
                    help="run the idle and flood attackers at this niceness (19: the CPU is the server's first, as "
                         "with a remote attacker); they share this machine's cores otherwise")
    ap.add_argument("--only", nargs="+", choices=SCENARIOS, default=SCENARIOS, help="these scenarios (default: all)")
    ap.add_argument("--json")
    args = ap.parse_args()
    global NICE
    NICE = args.attacker_nice
    print(f"{platform.node()}, {os.cpu_count()} CPUs; load average before: {os.getloadavg()[0]:.2f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        gan, vae = (args.gan, args.vae) if args.gan else demo_size_models(Path(tmp))
        server = Server({"gan": str(gan), "vae": str(vae)}, ["--workers", "1"])
        try:
            rows = run(server.port, args)
        finally:
            code = server.stop()
        noise = [line for line in server.lines if "Traceback" in line or "ERROR" in line]
    base = rows[0]["p50"]
    print(f"\nload average after: {os.getloadavg()[0]:.2f}; server exit {code}; server log lines with a traceback "
          f"or ERROR: {len(noise)}\n")
    print("| scenario | /healthz answered | p50 ms | p99 ms | max ms | max / baseline p50 |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['scenario']} | {r['ok']}/{r['sent']} | {r['p50']:.1f} | {r['p99']:.1f} | {r['max']:.1f} | "
              f"{r['max'] / base:.1f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "server_exit": code, "noise": noise}, indent=1))


if __name__ == "__main__":
    main()
