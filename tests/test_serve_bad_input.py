"""Hostile and mistaken requests against a real ``lsgan serve``, one table row each, then a seeded fuzz run.

Each row sends one request and checks: the status; a JSON body ``{"error": one line}`` holding the row's phrase
(or, for a 200 row, the phrase in the answer); that the server still answers /healthz; and, over the whole
file, that no request got a 5xx and the server logged no traceback.
"""
from __future__ import annotations

import http.client
import json
import random
import threading
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from serve_client import Server

pytestmark = pytest.mark.slow
KEY = "k3y-for-tests"
AUTH = {"Authorization": f"Bearer {KEY}"}
GEN = "/v1/generate"
UNKNOWN_ID = "0123456789abcdef0123456789abcdef"
BODY_LIMIT, TEXT_LIMIT, NUM_LIMIT = 2048, 200, 4


@pytest.fixture(scope="module")
def servers(serve_models: Path):
    """"text": the text GAN with small limits and a key; "action": the action GAN, one request in flight at most."""
    text = Server("--gan", "gan", "--vae", "vae", "--api-key", KEY, "--max-body-bytes", BODY_LIMIT,
                  "--max-text-chars", TEXT_LIMIT, "--max-num", NUM_LIMIT, cwd=serve_models)
    action = Server("--gan", "act-gan", "--vae", "vae", "--max-in-flight", 1, cwd=serve_models)
    both = {"text": text, "action": action}
    yield both
    codes = {name: s.stop() for name, s in both.items()}
    for name, s in both.items():
        assert "Traceback" not in s.stderr and "internal error" not in s.stderr, s.stderr
    assert codes == {"text": 0, "action": 0}


@dataclass(frozen=True)
class Case:
    id: str
    method: str
    path: str
    body: object = None  # dict/list: sent as JSON; bytes/str: raw; a callable: made from the server's /v1/info
    status: int = 422
    phrase: str = ""
    headers: dict = field(default_factory=lambda: {"Content-Type": "application/json", **AUTH})
    server: str = "text"
    chunked: bool = False


def J(**fields) -> bytes:
    return json.dumps(fields).encode()


def no_key(**headers) -> dict:
    return {"Content-Type": "application/json", **headers}


CASES = [
    # JSON itself
    Case("malformed-json", "POST", GEN, b'{"text": "walk"', 400, "malformed JSON"),
    Case("empty-body", "POST", GEN, b"", 400, "empty body"),
    Case("json-array", "POST", GEN, b'["a person walks"]', 422, "must be a JSON object"),
    Case("json-string", "POST", GEN, b'"a person walks"', 422, "not a string"),
    Case("json-null", "POST", GEN, b"null", 422, "not a null"),
    Case("nan-literal", "POST", GEN, b'{"text": "walk", "frames": NaN}', 400, "NaN is not JSON"),
    Case("infinity-literal", "POST", GEN, b'{"text": "walk", "seed": -Infinity}', 400, "Infinity is not JSON"),
    Case("not-utf8", "POST", GEN, b'{"text": "walk \xff\xfe"}', 400, "malformed JSON"),
    Case("nested-too-deep", "POST", GEN, b"[" * 1020 + b"]" * 1020, 400, "nested too deeply"),
    Case("duplicate-garbage-after", "POST", GEN, b'{"text": "walk"} {"text": "run"}', 400, "malformed JSON"),
    # wrong types (strict: no bool for int, no float or string for int, no list for text)
    Case("text-bool", "POST", GEN, J(text=True), 422, "text: input should be a valid string, got boolean"),
    Case("text-list", "POST", GEN, J(text=["a person walks"]), 422, "text: input should be a valid string, got array"),
    Case("text-number", "POST", GEN, J(text=5), 422, "text: input should be a valid string"),
    Case("text-object", "POST", GEN, J(text={"en": "walk"}), 422, "got object"),
    Case("frames-bool", "POST", GEN, J(text="walk", frames=True), 422, "frames: input should be a valid integer"),
    Case("frames-float", "POST", GEN, J(text="walk", frames=60.0), 422, "frames: input should be a valid integer"),
    Case("frames-string", "POST", GEN, J(text="walk", frames="60"), 422, "frames: input should be a valid integer"),
    Case("num-float", "POST", GEN, J(text="walk", num=1.5), 422, "num: input should be a valid integer"),
    Case("seed-string", "POST", GEN, J(text="walk", seed="7"), 422, "seed: input should be a valid integer"),
    Case("seed-exponent", "POST", GEN, b'{"text": "walk", "seed": 1e3}', 422, "seed: input should be a valid integer"),
    Case("unknown-field", "POST", GEN, J(text="walk", frame=60), 422, "frame: unknown field"),
    # huge, negative and out-of-range numbers
    Case("frames-googol", "POST", GEN, b'{"text": "walk", "frames": 1' + b"0" * 100 + b"}", 422,
         "frames must be 4 to 196"),
    Case("frames-negative", "POST", GEN, J(text="walk", frames=-5), 422, "frames must be 4 to 196, got -5"),
    Case("frames-zero", "POST", GEN, J(text="walk", frames=0), 422, "frames must be 4 to 196"),
    Case("frames-under-min", "POST", GEN, J(text="walk", frames=3), 422, "frames must be 4 to 196"),
    Case("frames-over-model", "POST", GEN, J(text="walk", frames=197), 422, "frames must be 4 to 196"),
    Case("num-zero", "POST", GEN, J(text="walk", num=0), 422, f"num must be 1 to {NUM_LIMIT}"),
    Case("num-over-limit", "POST", GEN, J(text="walk", num=NUM_LIMIT + 1), 422, f"num must be 1 to {NUM_LIMIT}"),
    Case("num-negative", "POST", GEN, J(text="walk", num=-1), 422, "num must be 1"),
    Case("seed-2-64", "POST", GEN, J(text="walk", seed=2**64), 422, "seed: input should be less than or equal"),
    Case("seed-negative", "POST", GEN, J(text="walk", seed=-1), 422, "seed: input should be greater than or equal"),
    # text and action
    Case("neither", "POST", GEN, J(frames=60), 422, "exactly one of"),
    Case("both", "POST", GEN, J(text="walk", action="walk"), 422, "exactly one of"),
    Case("text-null", "POST", GEN, J(text=None), 422, "exactly one of"),
    Case("action-to-text-model", "POST", GEN, J(action="walk"), 422, "conditioned on text"),
    Case("text-empty", "POST", GEN, J(text=""), 422, "text is empty"),
    Case("text-whitespace", "POST", GEN, J(text=" \n\t  "), 422, "text is empty"),
    Case("text-over-limit", "POST", GEN, J(text="a" * (TEXT_LIMIT + 1)), 422, f"the limit is {TEXT_LIMIT}"),
    Case("text-nul", "POST", GEN, J(text="walk\x00forward"), 422, "control character (U+0000)"),
    Case("text-escape-sequence", "POST", GEN, J(text="walk \x1b[31mred"), 422, "control character (U+001B)"),
    Case("text-lone-surrogate", "POST", GEN, b'{"text": "walk \\ud800 on"}', 422, "lone surrogate (U+D800)"),
    # printable unicode is a prompt like any other (the tokenizer reads what it knows of it)
    Case("text-emoji", "POST", GEN, J(text="a person dances \U0001F483\U0001F3FD with joy"), 200, '"motions"'),
    Case("text-rtl", "POST", GEN, J(text="\u0634\u062e\u0635 \u064a\u0645\u0634\u064a"), 200, '"motions"'),
    Case("text-rtl-override", "POST", GEN, J(text="walk \u202eforward"), 200, '"motions"'),
    Case("text-newline", "POST", GEN, J(text="a person\nwalks"), 200, '"motions"'),
    Case("seed-largest", "POST", GEN, J(text="walk", seed=2**53 - 1, frames=20), 200, '"seed":9007199254740991'),
    # actions (the action GAN)
    Case("unknown-action", "POST", GEN, J(action="fly"), 422, "unknown action 'fly'", server="action"),
    Case("action-number", "POST", GEN, J(action=3), 422, "action: input should be a valid string",
         server="action"),
    Case("text-to-action-model", "POST", GEN, J(text="walk"), 422, "conditioned on actions", server="action"),
    Case("known-action", "POST", GEN, lambda info: J(action=info["actions"][0], frames=40), 200, '"motions"',
         server="action"),
    # constraints (docs/control.md): the path and keyframe files' rules, then the model's reach
    Case("path-too-fast", "POST", GEN, J(text="walk", frames=40, path=[[0, 0], [50, 0]]), 422,
         "path: the root would move at 1000.0 m/s"),
    Case("path-ragged", "POST", GEN, J(text="walk", path=[[0, 0], [1, 2, 3]]), 422, "path: rows of different lengths"),
    Case("path-empty", "POST", GEN, J(text="walk", path=[]), 422, "path: no points"),
    Case("path-bool", "POST", GEN, J(text="walk", path=[[True, 0]]), 422, "path.0.0: input should be a valid number"),
    Case("path-strings", "POST", GEN, J(text="walk", path=[["0", "1"]]), 422, "path.0.0: input should be a valid number"),
    Case("path-flat", "POST", GEN, J(text="walk", path=[0, 1]), 422, "path.0: input should be a valid list"),
    Case("path-one-number", "POST", GEN, J(text="walk", path=[[0]]), 422, "path: rows of 2 or 3 numbers"),
    Case("path-late-start", "POST", GEN, J(text="walk", path=[[0.5, 0, 0], [1, 0, 1]]), 422,
         "a path starts with the motion, at 0 s"),
    Case("path-past-end", "POST", GEN, J(text="walk", frames=40, path=[[0, 0, 0], [5, 0, 1]]), 422,
         "the motion ends at 1.95 s"),
    Case("path-waypoints-too-close", "POST", GEN, J(text="walk", path=[[0, 0, 0], [0.01, 0, 0]]), 422,
         "less than a frame"),
    Case("path-too-many-points", "POST", GEN, J(text="walk", frames=10, path=[[0, 0]] * 11), 422,
         "11 points for a motion of 10 frames"),
    Case("path-huge", "POST", GEN, J(text="walk", path=[[0, 0], [1e300, 0]]), 422, "beyond 10000"),
    Case("path-overflowing-number", "POST", GEN, b'{"text": "walk", "path": [[0, 0], [1e999, 0]]}', 422,
         "beyond 10000"),
    Case("keyframe-beyond", "POST", GEN, J(text="walk", frames=40, keyframes=[
        {"frame": 400, "joints": {"pelvis": [0, 0.9, 0]}}]), 422, "keyframes[0]: keyframe 400 is not a frame of the "
         "motion: its 40 frames are 0..39"),
    Case("keyframe-negative", "POST", GEN, J(text="walk", keyframes=[{"frame": -1, "joints": {"head": [0, 1, 0]}}]),
         422, "keyframes[0]: keyframe -1 is not a frame of the motion"),
    Case("keyframe-below-ground", "POST", GEN, J(text="walk", keyframes=[{"frame": 5, "joints": {"head": [0, -3, 0]}}]),
         422, "keyframes[0]: keyframe 5: head at y = -3.00 m is below the ground"),
    Case("keyframe-joint-twice", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": {"21": [0.3, 1.2, 0.2], "right_wrist": [0.4, 1.2, 0.2]}}]), 422,
         "joint right_wrist is set twice"),
    Case("keyframe-all-null", "POST", GEN, J(text="walk", keyframes=[{"frame": 5, "joints": {"head": [None] * 3}}]),
         422, "sets no coordinate"),
    Case("keyframe-unicode-digit-joint", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": {"\u00b2": [0, 1, 0]}}]), 422, "unknown joint"),
    Case("duplicate-key", "POST", GEN, b'{"text": "walk", "frames": 80, "frames": 90}', 400,
         "the key 'frames' is given twice"),
    Case("keyframe-frame-0-root-x-only", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 0, "joints": {"pelvis": [0.5, None, None]}}]), 422, "on frame 0 is the motion's start"),
    Case("path-one-point", "POST", GEN, J(text="walk", path=[[0, 0]]), 422, "a path needs at least two points"),
    Case("num-over-control-limit", "POST", GEN, J(text="walk", num=3, path=[[0, 0], [0.05, 0]]), 422,
         "num must be 1 to 2 with constraints"),
    Case("keyframe-unknown-joint", "POST", GEN, J(text="walk", keyframes=[{"frame": 5, "joints": {"nose": [0, 1, 0]}}]),
         422, "keyframes[0]: unknown joint 'nose'"),
    Case("keyframe-two-coordinates", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": {"left_wrist": [0, 1]}}]), 422, "has 2 coordinates, not 3"),
    Case("keyframe-string-coordinate", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": {"head": ["1", 1, 1]}}]), 422, "keyframes.0.joints"),
    Case("keyframe-no-joint", "POST", GEN, J(text="walk", keyframes=[{"frame": 5, "joints": {}}]), 422,
         "with at least one joint"),
    Case("keyframe-wrong-skeleton", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": [[0.01 * j, 100.0 * (j % 3), 0.0] for j in range(22)]}]), 422,
         "a pose of another skeleton or in other units"),
    Case("keyframe-short-pose", "POST", GEN, J(text="walk", keyframes=[{"frame": 5, "joints": [[0, 0, 0]] * 21}]),
         422, "(22, 3) joints"),
    Case("keyframe-same-frame-twice", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": {"head": [0, 1.6, 0]}}, {"frame": 5, "joints": {"neck": [0, 1.4, 0]}}]), 422,
         "a second keyframe for frame 5"),
    Case("keyframe-without-frame", "POST", GEN, J(text="walk", keyframes=[{"joints": {"head": [0, 1.6, 0]}}]), 422,
         "keyframes.0.frame: field required"),
    Case("keyframe-frame-float", "POST", GEN, J(text="walk", keyframes=[{"frame": 5.0, "joints": {"head": [0, 1, 0]}}]),
         422, "keyframes.0.frame: input should be a valid integer"),
    Case("keyframe-extra-field", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 5, "joints": {"head": [0, 1.6, 0]}, "weight": 2}]), 422, "keyframes.0.weight"),
    Case("keyframes-empty", "POST", GEN, J(text="walk", keyframes=[]), 422, "keyframes: an empty list"),
    Case("keyframe-root-off-start", "POST", GEN, J(text="walk", keyframes=[
        {"frame": 0, "joints": {"pelvis": [1.0, 0.9, 0.0]}}]), 422, "keyframes[0]: keyframe 0's root on frame 0 is the "
         "motion's start"),
    Case("facing-without-path", "POST", GEN, J(text="walk", facing=True), 422, "facing: it turns the root along a path"),
    Case("facing-number", "POST", GEN, J(text="walk", path=[[0, 0], [0.05, 0]], facing=1), 422,
         "facing: input should be a valid boolean"),
    Case("continue-unknown-id", "POST", GEN, J(text="walk", continue_from=UNKNOWN_ID), 422,
         "continue_from: no motion"),
    Case("continue-with-path", "POST", GEN, J(text="walk", continue_from=UNKNOWN_ID, path=[[0, 0], [0.1, 0]]), 422,
         "send it without path and keyframes"),
    Case("continue-number", "POST", GEN, J(text="walk", continue_from=5), 422,
         "continue_from: input should be a valid string"),
    # how the body comes
    Case("content-type-text", "POST", GEN, J(text="walk"), 415, "Content-Type: application/json",
         headers={"Content-Type": "text/plain", **AUTH}),
    Case("content-type-missing", "POST", GEN, J(text="walk"), 415, "not 'none'", headers=dict(AUTH)),
    Case("content-type-form", "POST", GEN, b"text=walk", 415, "application/x-www-form-urlencoded",
         headers={"Content-Type": "application/x-www-form-urlencoded", **AUTH}),
    Case("body-over-limit", "POST", GEN, J(text="a" * (BODY_LIMIT + 10)), 413, f"over {BODY_LIMIT} bytes"),
    Case("body-over-limit-chunked", "POST", GEN, J(text="a" * (BODY_LIMIT + 10)), 413, f"over {BODY_LIMIT} bytes",
         chunked=True),
    # downloads: only ids of the store and three extensions; clients never name a path
    Case("unknown-id", "GET", f"/v1/motions/{UNKNOWN_ID}.glb", status=404, phrase="no motion"),
    Case("malformed-id", "GET", "/v1/motions/abc.bvh", status=404, phrase="no motion 'abc'"),
    Case("bad-extension", "GET", f"/v1/motions/{UNKNOWN_ID}.exe", status=404, phrase="unknown format 'exe'"),
    Case("no-extension", "GET", f"/v1/motions/{UNKNOWN_ID}", status=404, phrase="unknown format"),
    Case("traversal-id", "GET", "/v1/motions/..%2F..%2F..%2Fetc%2Fpasswd.npy", status=404, phrase="no such route"),
    Case("traversal-dots", "GET", "/v1/motions/....npy", status=404, phrase="no motion"),
    Case("static-traversal", "GET", "/static/..%2F..%2Fcli.py", status=404, phrase="no such route"),
    Case("static-dotdot", "GET", "/static/..", status=404, phrase="no page file"),
    Case("static-not-listed", "GET", "/static/engine.py", status=404, phrase="no page file 'engine.py'"),
    Case("static-absolute", "GET", "/static//etc/passwd", status=404, phrase="no such route"),
    # routes and methods
    Case("unknown-route", "GET", "/v2/generate", status=404, phrase="no such route: GET /v2/generate"),
    Case("unknown-v1-route", "GET", "/v1/nothing", status=404, phrase="no such route"),
    Case("get-generate", "GET", GEN, status=405, phrase="method GET not allowed"),
    Case("delete-generate", "DELETE", GEN, status=405, phrase="method DELETE not allowed"),
    Case("post-info", "POST", "/v1/info", J(), status=405, phrase="not allowed"),
    Case("put-healthz", "PUT", "/healthz", b"", status=405, phrase="not allowed"),
    # the key
    Case("no-key", "POST", GEN, J(text="walk"), 401, "needs an API key", headers=no_key()),
    Case("wrong-key", "POST", GEN, J(text="walk"), 401, "wrong API key", headers=no_key(Authorization="Bearer x")),
    Case("basic-auth", "POST", GEN, J(text="walk"), 401, "needs an API key",
         headers=no_key(Authorization="Basic dXNlcjpwYXNz")),
    Case("info-no-key", "GET", "/v1/info", status=401, phrase="needs an API key", headers={}),
    Case("download-no-key", "GET", f"/v1/motions/{UNKNOWN_ID}.npy", status=401, phrase="needs", headers={}),
    Case("healthz-open", "GET", "/healthz", status=200, phrase='"ok"', headers={}),
    Case("x-api-key", "GET", "/v1/info", status=200, phrase='"condition":"text"', headers={"X-API-Key": KEY}),
]


def send(server: Server, case: Case) -> tuple[int, dict, bytes]:
    body = case.body
    if callable(body):
        body = body(json.loads(server.request("GET", "/v1/info", headers=AUTH)[2]))
    if not case.chunked:
        return server.request(case.method, case.path, body, case.headers)
    conn = http.client.HTTPConnection(server.host, server.port, timeout=30)
    try:
        conn.request(case.method, case.path, body=iter([body[i:i + 500] for i in range(0, len(body), 500)]),
                     headers=case.headers, encode_chunked=True)
        resp = conn.getresponse()
        return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read()
    finally:
        conn.close()


def test_table_is_large_enough() -> None:
    assert len(CASES) >= 40 and len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_request(case: Case, servers: dict) -> None:
    server = servers[case.server]
    status, head, body = send(server, case)
    text = body.decode("utf-8")
    assert status == case.status, text
    if status == 200:
        assert case.phrase in text.replace(" ", "")
    else:
        assert head["content-type"] == "application/json"
        answer = json.loads(text)
        assert list(answer) == ["error"] and "\n" not in answer["error"] and "Traceback" not in answer["error"]
        assert case.phrase.lower() in answer["error"].lower(), answer
    assert head.get("x-content-type-options") == "nosniff"
    assert server.json("GET", "/healthz") == (200, {"status": "ok"})


def test_busy_gets_503_with_retry_after(servers: dict) -> None:
    """The action server admits one request at a time: of 16 sent at once, the first is admitted and answered,
    those that arrive while it is in flight get 503 with Retry-After at once."""
    s = servers["action"]
    action = json.loads(s.request("GET", "/v1/info")[2])["actions"][0]
    replies: list = [None] * 16
    barrier = threading.Barrier(len(replies))

    def send(i: int) -> None:
        barrier.wait()
        replies[i] = s.request("POST", GEN, {"action": action, "frames": 196, "num": 8})

    threads = [threading.Thread(target=send, args=(i,)) for i in range(len(replies))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    statuses = sorted(r[0] for r in replies)
    assert set(statuses) == {200, 503} and statuses.count(200) >= 1, statuses
    busy = [r for r in replies if r[0] == 503]
    assert all(r[1]["retry-after"] == "1" and "server busy" in json.loads(r[2])["error"] for r in busy)


def test_timeout_gets_503(serve_models: Path) -> None:
    """A request that cannot be answered within --timeout (1 ms; a pass of 8 motions of 196 frames takes more):
    503 with Retry-After, and the server goes on."""
    s = Server("--gan", "gan", "--vae", "vae", "--timeout", 0.001, cwd=serve_models)
    try:
        status, head, body = s.request("POST", GEN, {"text": "walk", "frames": 196, "num": 8})
        assert status == 503 and head["retry-after"] == "2"
        assert "timed out after 0.001 s" in json.loads(body)["error"]
        assert s.json("GET", "/healthz") == (200, {"status": "ok"})
    finally:
        assert s.stop() == 0, s.stderr


def fuzz_value(rng: random.Random, depth: int = 0):
    kinds = ["int", "big", "float", "str", "bool", "null"] + (["list", "dict"] if depth < 3 else [])
    kind = rng.choice(kinds)
    if kind == "int":
        return rng.randint(-300, 300)
    if kind == "big":
        return rng.choice([-1, 1]) * 10 ** rng.randint(10, 400)
    if kind == "float":
        return rng.uniform(-1e6, 1e6)
    if kind == "str":
        return "".join(chr(rng.choice([rng.randint(0, 0x7F), rng.randint(0x80, 0x2FFF), rng.randint(0x1F300, 0x1FAFF)]))
                       for _ in range(rng.randint(0, 30)))
    if kind == "bool":
        return rng.random() < 0.5
    if kind == "null":
        return None
    if kind == "list":
        return [fuzz_value(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    keys = ["text", "action", "frames", "num", "seed", "x", ""]
    return {rng.choice(keys): fuzz_value(rng, depth + 1) for _ in range(rng.randint(0, 5))}


def test_fuzz_never_5xx(servers: dict) -> None:
    """300 seeded random requests (random bytes, random JSON, valid-looking bodies with random values, random
    paths and methods): never a 5xx, and the server keeps answering."""
    s, rng, seen = servers["text"], random.Random(13), {}
    paths = [GEN, "/v1/info", "/healthz", f"/v1/motions/{UNKNOWN_ID}.glb", "/static/x", "/", "/v1/motions/%00.npy"]
    for i in range(300):
        roll = rng.random()
        if roll < 0.3:
            body = bytes(rng.randrange(256) for _ in range(rng.randint(0, 200)))
        elif roll < 0.6:
            body = json.dumps(fuzz_value(rng)).encode()
        else:
            body = json.dumps({"text": fuzz_value(rng) if rng.random() < 0.5 else "a person walks",
                               **{k: fuzz_value(rng) for k in rng.sample(["frames", "num", "seed"], rng.randint(0, 3))}
                               }).encode()
        method = rng.choice(["POST"] * 6 + ["GET", "PUT", "PATCH", "DELETE", "OPTIONS"])
        path = GEN if method == "POST" and rng.random() < 0.9 else rng.choice(paths)
        status, _, _ = s.request(method, path, body if method != "GET" else None,
                                 {"Content-Type": rng.choice(["application/json"] * 4 + ["text/plain"]), **AUTH})
        seen[status] = seen.get(status, 0) + 1
        assert status < 500, (i, method, path, body[:200])
    assert s.json("GET", "/healthz") == (200, {"status": "ok"})
    assert seen.get(422, 0) > 50 and seen.get(400, 0) > 30 and seen.get(200, 0) > 0, seen
