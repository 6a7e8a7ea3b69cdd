"""Load on ``lsgan serve``: 1, 8 and 32 concurrent clients, then the same work one request at a time in-process.

Starts a real server (a subprocess, 127.0.0.1 only, a free port) on demo-size models (``--gan/--vae``, e.g. a
Bandai-Namco run, which has recipes/demo.yaml's sizes; without them, demo-size models are made in a few seconds
with two training steps each: their speed is the trained ones', their motions are noise). Each client is a
thread with a keep-alive connection that sends POST /v1/generate (a prompt from a fixed list, ``--frames``, a
random seed) as soon as its previous answer has arrived, for ``--seconds`` per level. Reported per level:
requests/s, latency p50/p95/p99 (send to last byte), errors (anything but a 200, or a failed connection), the
mean engine batch size, and the server's peak memory so far (VmHWM, its process and its engine processes added).
Then ``engine.run`` of the same kind of request one at a time in this process, for as long. The 1-minute load
average is printed at the start and the end, and each level's machine speed: the int8 rate of this machine right
before and after each of its slices. The host can slow this machine unseen for seconds, which would bend the
levels' ratio, so each level runs as ``--rounds`` slices taken in turn with the others (1, 8, 32, 32, 8, 1, ...):
a slow stretch then falls on all of them alike; the ratio of each round is printed too.

    python benchmarks/serve.py --gan runs/bandai-gan --vae runs/bandai-vae
    python benchmarks/serve.py --clients 1,8,32 --seconds 20 --rounds 4 --json serve.json
    python benchmarks/serve.py --model bandai-onnx --int8 --unique-prompts   # an export-model folder
"""
from __future__ import annotations

import argparse
import http.client
import json
import os
import platform
import random
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROMPTS = [
    "a person walks forward", "a person runs forward", "a person waves their right hand", "a person jumps up",
    "a person does a squat", "a person walks happily", "a person walks tiredly with the head down",
    "someone raises both hands above the head", "a person kicks with the left leg", "a person turns around",
    "a man walks in a circle and then stops", "a person dances with both arms moving",
    "a woman walks forward proudly", "someone steps to the side and back", "a person bows politely",
    "a person punches forward with the right hand",
]


def lsgan(*args, cwd: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], cwd=cwd, capture_output=True, text=True)
    if out.returncode:
        sys.exit(f"lsgan {args[0]} failed: {out.stderr.strip().splitlines()[-1:]}")


def demo_size_models(d: Path) -> tuple[Path, Path]:
    """A VAE and a GAN with recipes/demo.yaml's sizes after two training steps each (speed only)."""
    recipe = ROOT / "recipes" / "demo.yaml"
    lsgan("preprocess", "--source", "synthetic", "--num-clips", 40, "-o", "synth.h5", cwd=d)
    lsgan("train-vae", "--data", "synth.h5", "--recipe", recipe, "--out", "vae", "--max-steps", 2, cwd=d)
    lsgan("encode-latents", "--data", "synth.h5", "--vae", "vae", "-o", "cache.h5", cwd=d)
    lsgan("train-gan", "--cache", "cache.h5", "--recipe", recipe, "--out", "gan", "--max-steps", 2, cwd=d)
    return d / "gan", d / "vae"


def serve_options(models: dict[str, str | bool]) -> list[str]:
    """``load_engine``'s keywords (gan and vae, or model and int8) as ``lsgan serve`` options."""
    return [x for k, v in models.items() if v for x in ([f"--{k}"] if v is True else [f"--{k}", str(v)])]


class Server:
    """``lsgan serve`` on 127.0.0.1, a free port."""

    def __init__(self, models: dict[str, str | bool], extra: list[str]) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "lsgan.cli", "serve", *serve_options(models),
                                      "--host", "127.0.0.1", "--port", "0", *extra], stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        threading.Thread(target=lambda: [self.lines.append(x.rstrip()) for x in self.proc.stderr], daemon=True).start()
        deadline = time.monotonic() + 300
        while not (found := [m for x in list(self.lines) if (m := re.search(r"http://[^ ]*:(\d+)/ ", x))]):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.proc.kill()
                sys.exit("the server did not start:\n" + "\n".join(self.lines))
            time.sleep(0.1)
        self.port = int(found[0].group(1))

    def pids(self) -> list[int]:
        """The server and its children (the engine processes, lsgan.serve.worker)."""
        children = []
        for task in Path(f"/proc/{self.proc.pid}/task").iterdir():
            try:
                children += (task / "children").read_text().split()
            except OSError:
                pass
        return [self.proc.pid, *sorted(set(map(int, children)))]

    def peak_rss_mb(self) -> float:
        """The peak resident memory of the server and its engine processes, added."""
        total = 0
        for pid in self.pids():
            text = Path(f"/proc/{pid}/status").read_text()
            total += int(re.search(r"VmHWM:\s+(\d+) kB", text).group(1))
        return total / 1024

    def cpu_s(self) -> float:
        """CPU seconds the server and its engine processes have used (all their threads)."""
        ticks = 0
        for pid in self.pids():
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            ticks += int(fields[11]) + int(fields[12])
        return ticks / os.sysconf("SC_CLK_TCK")

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(60)


def prompt(rng: random.Random, unique: bool) -> str:
    """One of PROMPTS, or with --unique-prompts a sentence never sent before (no prompt cache hit)."""
    return f"{rng.choice(PROMPTS)}, take {rng.randrange(10**9)}" if unique else rng.choice(PROMPTS)


def client(port: int, frames: int, until: float, rng: random.Random, out: dict, unique: bool) -> None:
    """Requests back to back on one keep-alive connection until ``until``; latencies and errors into ``out``."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    while time.perf_counter() < until:
        body = json.dumps({"text": prompt(rng, unique), "frames": frames, "seed": rng.randrange(2**31)})
        t0 = time.perf_counter()
        try:
            conn.request("POST", "/v1/generate", body, {"Content-Type": "application/json"})
            resp = conn.getresponse()
            data = resp.read()
            ok = resp.status == 200
        except (OSError, http.client.HTTPException):
            conn.close()
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            ok, data = False, b""
        out["latencies"].append(time.perf_counter() - t0)
        if ok:
            batch = re.search(rb'"batch_size":(\d+)}$', data)
            out["batches"].append(int(batch.group(1)) if batch else 0)
        else:
            out["errors"] += 1
    conn.close()


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * len(ordered)) - 1))] if ordered else float("nan")


def level(server: Server, clients: int, seconds: float, frames: int, seed: int, unique: bool) -> dict:
    """``clients`` concurrent clients for ``seconds``: what they measured (latencies, engine batch sizes, errors),
    the CPU seconds of the server and of the clients, and the machine's int8 rate right before and after
    (:func:`lsgan.eval.bench.machine_rate`, the server idle)."""
    from lsgan.eval.bench import machine_rate

    time.sleep(0.5)  # the server settles after the last slice (its passes' thread policy: lsgan.serve.batcher)
    before = machine_rate()
    outs = [{"latencies": [], "batches": [], "errors": 0} for _ in range(clients)]
    server_cpu, own_cpu = server.cpu_s(), sum(os.times()[:2])
    start = time.perf_counter()
    threads = [threading.Thread(target=client, args=(server.port, frames, start + seconds,
                                                     random.Random(seed * 1000 + i), outs[i], unique))
               for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    elapsed = time.perf_counter() - start
    return {"clients": clients, "seconds": elapsed, "latencies": [x for o in outs for x in o["latencies"]],
            "batches": [x for o in outs for x in o["batches"]], "errors": sum(o["errors"] for o in outs),
            "server_cpu_s": server.cpu_s() - server_cpu, "client_cpu_s": sum(os.times()[:2]) - own_cpu,
            "machine_int8_gops": [before, machine_rate()]}


def summary(slices: list[dict], server: Server) -> dict:
    """One level's slices as one row: requests/s over their time, pooled latency percentiles, errors, mean batch,
    peak memory, cores used, the machine rates measured around them, and each slice's requests/s."""
    lat = [x for r in slices for x in r["latencies"]]
    batches = [x for r in slices for x in r["batches"]]
    seconds = sum(r["seconds"] for r in slices)
    return {"clients": slices[0]["clients"], "requests": len(lat), "seconds": seconds, "rps": len(lat) / seconds,
            "p50_ms": 1e3 * percentile(lat, 50), "p95_ms": 1e3 * percentile(lat, 95),
            "p99_ms": 1e3 * percentile(lat, 99), "errors": sum(r["errors"] for r in slices),
            "mean_batch": statistics.fmean(batches) if batches else 0.0, "server_peak_rss_mb": server.peak_rss_mb(),
            "server_cpu_cores": sum(r["server_cpu_s"] for r in slices) / seconds,
            "client_cpu_cores": sum(r["client_cpu_s"] for r in slices) / seconds,
            "machine_int8_gops": [x for r in slices for x in r["machine_int8_gops"]],
            "rps_per_round": [len(r["latencies"]) / r["seconds"] for r in slices]}


def interleaved(server: Server, levels: list[int], seconds: float, rounds: int, frames: int, unique: bool) -> list[dict]:
    """Each level for ``seconds`` in all, as ``rounds`` slices taken in turn (1, 8, 32, then 32, 8, 1, ...), so that
    a stretch of a slow host (README, Benchmarks) falls on every level alike instead of bending their ratio."""
    slices: dict[int, list[dict]] = {n: [] for n in levels}
    for k in range(rounds):
        for n in (levels if k % 2 == 0 else levels[::-1]):
            slices[n].append(level(server, n, seconds / rounds, frames, seed=n * 100 + k, unique=unique))
    return [summary(slices[n], server) for n in levels]


def in_process(models: dict[str, str | bool], seconds: float, frames: int, unique: bool) -> dict:
    """``engine.run`` of one request at a time in this process, for ``seconds`` (the server's prompt cache too)."""
    from lsgan.serve.engine import Item, load_engine

    engine = load_engine(**models)
    rng, lat = random.Random(1), []
    until = time.perf_counter() + seconds
    start = time.perf_counter()
    while time.perf_counter() < until:
        t0 = time.perf_counter()
        engine.run([Item(text=prompt(rng, unique), frames=frames, seed=rng.randrange(2**31))])
        lat.append(time.perf_counter() - t0)
    elapsed = time.perf_counter() - start
    return {"requests": len(lat), "seconds": elapsed, "rps": len(lat) / elapsed, "p50_ms": 1e3 * percentile(lat, 50),
            "p95_ms": 1e3 * percentile(lat, 95), "p99_ms": 1e3 * percentile(lat, 99)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gan", type=Path, help="GAN run (default: demo-size models made for the benchmark)")
    parser.add_argument("--vae", type=Path)
    parser.add_argument("--model", type=Path, help="an `lsgan export-model --onnx` folder instead (onnxruntime)")
    parser.add_argument("--int8", action="store_true", help="--model: its int8 decoder")
    parser.add_argument("--clients", default="1,8,32", help="concurrent clients per level, comma-separated")
    parser.add_argument("--seconds", type=float, default=20.0, help="per level, and for the in-process run")
    parser.add_argument("--rounds", type=int, default=4,
                        help="slices per level, the levels taken in turn (1: each level in one go, as before)")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--unique-prompts", action="store_true",
                        help="every request a sentence never sent before (default: the 16 of PROMPTS, which the "
                             "server's prompt-embedding cache then holds)")
    parser.add_argument("--server-args", default="", help="more `lsgan serve` options, e.g. '--gather-ms 2'")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    if (args.gan is None) != (args.vae is None):
        parser.error("give both --gan and --vae, or neither")
    if args.model and args.gan or args.int8 and not args.model:
        parser.error("give --gan and --vae, or --model [--int8]")
    levels = [int(c) for c in args.clients.split(",")]
    load_start = os.getloadavg()[0]
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; load average (1 min) "
          f"at start {load_start:.2f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        if args.model:
            models: dict[str, str | bool] = {"model": str(args.model), "int8": args.int8}
        else:
            gan, vae = (args.gan, args.vae) if args.gan else demo_size_models(Path(tmp))
            models = {"gan": str(gan), "vae": str(vae)}
        server = Server(models, args.server_args.split())
        try:
            for n in levels:  # warm-up: every level a moment, so that no slice pays for the server's first passes
                level(server, n, 2.0, args.frames, seed=0, unique=args.unique_prompts)
            rows = interleaved(server, levels, args.seconds, args.rounds, args.frames, args.unique_prompts)
            for r in rows:
                print(f"{r['clients']:>3} clients: {r['rps']:7.1f} req/s  p50 {r['p50_ms']:6.1f}  "
                      f"p95 {r['p95_ms']:6.1f}  p99 {r['p99_ms']:6.1f} ms  errors {r['errors']}  "
                      f"mean batch {r['mean_batch']:.1f}  server peak RSS {r['server_peak_rss_mb']:.0f} MB  "
                      f"CPU: server {r['server_cpu_cores']:.2f}, clients {r['client_cpu_cores']:.2f} cores; "
                      f"machine {min(r['machine_int8_gops']):.0f}-{max(r['machine_int8_gops']):.0f} GOP/s; "
                      f"per round {' '.join(f'{x:.0f}' for x in r['rps_per_round'])} req/s", flush=True)
        finally:
            code = server.stop()
        seq = in_process(models, args.seconds, args.frames, args.unique_prompts)
    print(f"in-process, one request at a time (engine.run): {seq['rps']:.1f} req/s  p50 {seq['p50_ms']:.1f}  "
          f"p95 {seq['p95_ms']:.1f}  p99 {seq['p99_ms']:.1f} ms")
    best = max(rows, key=lambda r: r["clients"])
    per_round = [x / y for x, y in zip(best["rps_per_round"], rows[0]["rps_per_round"])]
    print(f"{best['clients']} clients over HTTP: {best['rps'] / rows[0]['rps']:.2f}x the {rows[0]['clients']}-client "
          f"rate (round by round {min(per_round):.2f}-{max(per_round):.2f}x), {best['rps'] / seq['rps']:.2f}x "
          f"sequential in-process; server exit code {code}")
    load_end = os.getloadavg()[0]
    print(f"load average (1 min) at end {load_end:.2f}")
    if args.json:
        args.json.write_text(json.dumps({
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
            "load_average_1min": {"start": load_start, "end": load_end}, "frames": args.frames,
            "prompts": "unique" if args.unique_prompts else f"{len(PROMPTS)} repeated",
            "seconds": args.seconds, "rounds": args.rounds,
            "models": models if args.model or args.gan else {"gan": "demo-size, untrained"},
            "levels": rows, "in_process": seq, "server_exit_code": code}, indent=1))


if __name__ == "__main__":
    main()
