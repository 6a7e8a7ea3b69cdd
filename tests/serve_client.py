"""A real ``lsgan serve`` in a subprocess on a free loopback port, and a plain HTTP client for it (http.client)."""
from __future__ import annotations

import http.client
import json
import os
import shutil
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

STARTUP_S = 60.0
THREE_CHECK = Path(__file__).resolve().parents[1] / "tools" / "three-check"
CHROMIUM = Path("/usr/bin/chromium")


class Server:
    """``lsgan serve ARGS --port 0``; its stderr is collected line by line (``self.lines``)."""

    def __init__(self, *args, cwd: Path, host: str = "127.0.0.1", env: dict | None = None) -> None:
        full_env = {k: v for k, v in os.environ.items() if k not in ("LSGAN_DEBUG", "LSGAN_API_KEY")}
        full_env.update({"OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", **(env or {})})
        self.proc = subprocess.Popen([sys.executable, "-m", "lsgan.cli", "serve", *map(str, args), "--host", host,
                                      "--port", "0"], cwd=cwd, env=full_env, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.port = self._wait_port()
        self.host = "127.0.0.1"

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))

    @property
    def stderr(self) -> str:
        return "\n".join(self.lines)

    def _wait_port(self) -> int:
        deadline = time.monotonic() + STARTUP_S
        while time.monotonic() < deadline:
            for line in list(self.lines):
                found = re.search(r"http://[^ ]*:(\d+)/ ", line)
                if found:
                    return int(found.group(1))
            if self.proc.poll() is not None:
                self._reader.join(5)
                raise AssertionError(f"lsgan serve exited with {self.proc.returncode}:\n{self.stderr}")
            time.sleep(0.05)
        self.stop()
        raise AssertionError(f"lsgan serve did not start in {STARTUP_S:g} s:\n{self.stderr}")

    def request(self, method: str, path: str, body=None, headers: dict | None = None,
                timeout: float = 30.0) -> tuple[int, dict, bytes]:
        """(status, headers with lower-case names, body) of one request on a fresh connection."""
        if isinstance(body, (dict, list)):
            body = json.dumps(body).encode()
            headers = {"Content-Type": "application/json", **(headers or {})}
        conn = http.client.HTTPConnection(self.host, self.port, timeout=timeout)
        try:
            conn.request(method, path, body=body, headers=headers or {})
            resp = conn.getresponse()
            return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read()
        finally:
            conn.close()

    def json(self, method: str, path: str, body=None, headers: dict | None = None) -> tuple[int, dict]:
        status, _, data = self.request(method, path, body, headers)
        return status, json.loads(data)

    def generate(self, **fields) -> dict:
        status, out = self.json("POST", "/v1/generate", fields)
        assert status == 200, out
        return out

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(5)
        return self.proc.returncode


def missing_browser() -> str | None:
    """Why the page cannot be driven here, or None."""
    if shutil.which("node") is None:
        return "node is not installed: the page is driven from Node (CI installs it)"
    if not CHROMIUM.exists():
        return f"no {CHROMIUM}: install it with `apt-get install -y chromium chromium-driver` (CI does)"
    if not (THREE_CHECK / "node_modules" / "playwright-core").exists():
        return "playwright-core is not installed: run `npm ci` in tools/three-check (CI does)"
    return None
