"""``lsgan serve`` for real: a uvicorn subprocess on a free loopback port, serving tiny trained models (conftest's
``serve_models``), driven over HTTP. Motions are compared through the exact ``.npy`` downloads."""
from __future__ import annotations

import io
import json
import threading
from pathlib import Path

import numpy as np
import pytest
from cli_runs import lsgan
from serve_client import Server

from lsgan.data.skeleton import JOINT_NAMES, KINEMATIC_CHAIN, PARENTS
from lsgan.export.bvh import joints_to_bvh

pytestmark = pytest.mark.slow
SAME = 1e-5  # metres: "the same motion" (joints), between batched/alone passes and against lsgan generate
PROMPT = "a person walks forward"


@pytest.fixture(scope="module")
def server(serve_models: Path):
    """The text GAN under torch; a 50 ms gathering window, so that concurrent requests share passes."""
    s = Server("--gan", "gan", "--vae", "vae", "--gather-ms", 50, cwd=serve_models)
    yield s
    assert s.stop() == 0, s.stderr


def npy(server: Server, motion: dict, headers: dict | None = None) -> np.ndarray:
    status, head, data = server.request("GET", motion["urls"]["npy"], headers=headers)
    assert status == 200 and head["content-type"] == "application/octet-stream"
    return np.load(io.BytesIO(data), allow_pickle=False)


def test_health_info_and_schema(server: Server) -> None:
    assert server.json("GET", "/healthz") == (200, {"status": "ok"})
    status, info = server.json("GET", "/v1/info")
    assert status == 200
    assert (info["condition"], info["actions"], info["fps"], info["auth"]) == ("text", [], 20.0, False)
    assert (info["min_frames"], info["default_frames"], info["max_frames"]) == (4, 120, 196)  # tiny VAE: max_len 200
    assert info["limits"]["max_num"] == 8 and info["limits"]["gather_ms"] == 50
    sk = info["skeleton"]
    assert sk["names"] == list(JOINT_NAMES) and sk["parents"] == list(PARENTS)
    assert sk["chains"] == [list(c) for c in KINEMATIC_CHAIN]
    assert sk["chain_colours"] == ["#dc2828", "#1e5adc", "#3c3c3c", "#dc2828", "#1e5adc"]  # right red, left blue
    status, schema = server.json("GET", "/openapi.json")
    body = schema["paths"]["/v1/generate"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    assert status == 200 and set(body["properties"]) == {"text", "action", "frames", "num", "seed", "path", "facing",
                                                         "keyframes", "continue_from"}
    assert "GenerateResponse" in json.dumps(schema["paths"]["/v1/generate"]["post"]["responses"]["200"])
    status, _, page = server.request("GET", "/docs")
    assert status == 200 and b"openapi.json" in page


def test_motions_equal_lsgan_generates(server: Server, serve_models: Path, tmp_path: Path) -> None:
    """POST /v1/generate and ``lsgan generate`` with the same prompt, length, num and seed: the same joints within
    SAME (1e-5 m), compared on the exact .npy downloads; the JSON joints are those rounded to 0.1 mm."""
    out = server.generate(text=PROMPT, frames=48, num=2, seed=3)
    assert (out["seed"], out["fps"], len(out["motions"])) == (3, 20.0, 2)
    assert set(out["timings_ms"]) == {"queue", "text", "generator", "decoder", "control", "total"}
    assert out["timings_ms"]["control"] == 0 and "control" not in out["motions"][0]
    assert out["timings_ms"]["total"] >= out["timings_ms"]["queue"] >= 0 and out["batch_size"] >= 2
    done = lsgan("generate", "--gan", "gan", "--vae", "vae", "--text", PROMPT, "--frames", 48, "--num", 2,
                 "--seed", 3, "-o", tmp_path / "gen", cwd=serve_models)
    assert done.returncode == 0, done.stderr
    manifest = json.loads((tmp_path / "gen" / "manifest.json").read_text())
    for motion, entry in zip(out["motions"], manifest["motions"], strict=True):
        ref = np.load(tmp_path / "gen" / entry["joints"])
        got = npy(server, motion)
        assert got.shape == ref.shape == (48, 22, 3) and got.dtype == np.float32 and motion["frames"] == 48
        assert np.abs(got - ref).max() < SAME
        assert np.abs(np.array(motion["joints"]) - got).max() <= 0.5e-4 + 1e-7
    assert np.abs(npy(server, out["motions"][0]) - npy(server, out["motions"][1])).max() > 1e-3  # two draws


def test_same_seed_same_motion_alone_or_batched(server: Server) -> None:
    """Requests of mixed prompts, lengths and nums, sent one at a time and then all at once: batched with others
    (and decoded in one padded batch of different lengths), each gives the motions it gives alone, within SAME."""
    asks = [dict(text=t, frames=f, num=n, seed=s) for t, f, n, s in [
        (PROMPT, 40, 1, 0), ("a man jumps twice", 196, 2, 1), ("someone waves the left hand", 64, 1, 2),
        (PROMPT, 120, 3, 3), ("kick", 17, 1, 4), ("a person squats down slowly", 150, 2, 5), (PROMPT, 40, 1, 6),
        ("a woman runs in a circle", 90, 1, 7)]]
    alone = []
    for ask in asks:
        out = server.generate(**ask)
        assert out["batch_size"] == ask["num"]  # it had the pass to itself
        alone.append([npy(server, m) for m in out["motions"]])
    together: list[dict | None] = [None] * len(asks)
    barrier = threading.Barrier(len(asks))

    def send(i: int) -> None:
        barrier.wait()
        together[i] = server.generate(**asks[i])

    threads = [threading.Thread(target=send, args=(i,)) for i in range(len(asks))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert all(together), "a concurrent request failed"
    assert max(out["batch_size"] - ask["num"] for out, ask in zip(together, asks)) > 0, "nothing was batched"
    for ask, out, ref in zip(asks, together, alone):
        got = [npy(server, m) for m in out["motions"]]
        assert [g.shape[0] for g in got] == [ask["frames"]] * ask["num"]
        assert max(np.abs(g - r).max() for g, r in zip(got, ref)) < SAME, ask


def test_constraints_equal_lsgan_generate(server: Server, serve_models: Path, tmp_path: Path) -> None:
    """A path with a keyframe, then a continuation of that motion by its id: each answer says how far its motions
    are from the constraints (the path met to float precision), and equals ``lsgan generate --path --keyframe`` and
    ``--continue`` (given the first motion's .npy download) with the same seed within SAME."""
    path = [[0.0, 0.0, 0.0], [1.0, 0.4, 0.6], [1.95, 0.5, 1.4]]
    hand = {"left_wrist": [0.5, 1.1, 0.7]}
    status, info = server.json("GET", "/v1/info")
    assert info["control"]["steers"] is True and info["control"]["max_speed_m_s"] > 1
    first = server.generate(text=PROMPT, frames=40, seed=5, path=path, keyframes=[{"frame": 20, "joints": hand}])
    got = npy(server, first["motions"][0])
    assert first["motions"][0]["control"]["path_m"]["max"] < 1e-4 and "placement" not in first
    assert first["timings_ms"]["control"] > 0 and first["batch_size"] == 1
    (tmp_path / "path.json").write_text(json.dumps(path))
    (tmp_path / "hand.json").write_text(json.dumps(hand))
    done = lsgan("generate", "--gan", "gan", "--vae", "vae", "--text", PROMPT, "--frames", 40, "--seed", 5,
                 "--path", tmp_path / "path.json", "--keyframe", f"20:{tmp_path / 'hand.json'}", "-o", tmp_path / "a",
                 cwd=serve_models)
    assert done.returncode == 0, done.stderr
    entry = json.loads((tmp_path / "a" / "manifest.json").read_text())["motions"][0]
    assert np.abs(got - np.load(tmp_path / "a" / entry["joints"])).max() < SAME
    assert entry["control"]["keyframes_m"]["max"] == pytest.approx(first["motions"][0]["control"]["keyframes_m"]["max"],
                                                                  abs=SAME)

    then = server.generate(text="a person sits down", frames=30, seed=6, continue_from=first["motions"][0]["id"])
    cont = npy(server, then["motions"][0])
    assert set(then["placement"]) == {"yaw_rad", "x_m", "z_m"}
    assert np.abs(cont[:5] - got[-5:]).max() < 0.03  # it starts where the first motion ends
    np.save(tmp_path / "first.npy", got)
    done = lsgan("generate", "--gan", "gan", "--vae", "vae", "--text", "a person sits down", "--frames", 30,
                 "--seed", 6, "--continue", tmp_path / "first.npy", "-o", tmp_path / "b", cwd=serve_models)
    assert done.returncode == 0, done.stderr
    entry = json.loads((tmp_path / "b" / "manifest.json").read_text())["motions"][0]
    assert np.abs(cont - np.load(tmp_path / "b" / entry["joints"])).max() < SAME


def test_glb_from_the_api_passes_the_khronos_validator(server: Server, tmp_path: Path) -> None:
    from gltf_reader import validate

    motion = server.generate(text="a person waves", frames=40, seed=1)["motions"][0]
    status, head, data = server.request("GET", motion["urls"]["glb"])
    assert status == 200 and head["content-type"] == "model/gltf-binary"
    assert head["content-disposition"] == f'attachment; filename="a-person-waves-{motion["id"][:8]}.glb"'
    (tmp_path / "m.glb").write_bytes(data)
    report = validate(tmp_path / "m.glb")
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]


def test_bvh_from_the_api_reimports_within_1mm(server: Server, tmp_path: Path) -> None:
    """lsgan's BVH reader on the served file poses the same skeleton as the served GLB (within 1 mm), keeps the
    root path of the exact joints (within 1 mm), and the file is the exporter's own output for those joints."""
    from gltf_reader import frame_count, node_index, parse, world_matrices

    from lsgan.data.bvh import forward_kinematics, read_bvh

    motion = server.generate(text="a person waves", frames=40, seed=2)["motions"][0]
    status, head, bvh = server.request("GET", motion["urls"]["bvh"])
    assert status == 200 and head["content-type"].startswith("text/plain")
    assert head["content-disposition"].endswith('.bvh"')
    joints = npy(server, motion)
    assert bvh.decode() == joints_to_bvh(joints, fps=20.0)
    (tmp_path / "m.bvh").write_bytes(bvh)
    reader = read_bvh(tmp_path / "m.bvh")
    from_bvh = forward_kinematics(reader)[:, [reader.names.index(n) for n in JOINT_NAMES]] / 100.0
    doc, blob = parse(server.request("GET", motion["urls"]["glb"])[2])
    index = [node_index(doc)[n] for n in JOINT_NAMES]
    from_glb = np.stack([world_matrices(doc, blob, t)[index, :3, 3] for t in range(frame_count(doc, blob))])
    assert from_bvh.shape == from_glb.shape == joints.shape
    assert np.abs(from_bvh - from_glb).max() < 1e-3
    assert np.abs(from_bvh[:, 0] - joints[:, 0]).max() < 1e-3


def test_onnx_model_behind_an_api_key(serve_models: Path, tmp_path: Path) -> None:
    """``--model DIR`` (onnxruntime) with ``--api-key``: /v1 needs the key (401 without it or with another one),
    the motions equal ``lsgan generate --runtime onnx`` with the same seed within SAME."""
    key = "s3cret-key"
    s = Server("--model", "gan-onnx", "--api-key", key, cwd=serve_models)
    try:
        ask = {"text": "someone jumps", "frames": 60, "num": 2, "seed": 11}
        assert s.json("GET", "/healthz") == (200, {"status": "ok"})  # open without a key
        for headers, phrase in [({}, "needs an API key"), ({"Authorization": "Bearer nope"}, "wrong API key"),
                                ({"X-API-Key": key + "x"}, "wrong API key"), ({"Authorization": key}, "needs")]:
            status, head, body = s.request("POST", "/v1/generate", ask, headers)
            assert status == 401 and phrase in json.loads(body)["error"] and head["www-authenticate"] == "Bearer"
        status, info = s.json("GET", "/v1/info", headers={"X-API-Key": key})
        assert status == 200 and info["auth"] is True and info["max_frames"] == 196
        status, out = s.json("POST", "/v1/generate", ask, {"Authorization": f"Bearer {key}"})
        assert status == 200, out
        assert s.request("GET", out["motions"][0]["urls"]["npy"])[0] == 401
        done = lsgan("generate", "--runtime", "onnx", "--gan", "gan-onnx", "--text", ask["text"], "--frames", 60,
                     "--num", 2, "--seed", 11, "-o", tmp_path / "gen", cwd=serve_models)
        assert done.returncode == 0, done.stderr
        entries = json.loads((tmp_path / "gen" / "manifest.json").read_text())["motions"]
        for motion, entry in zip(out["motions"], entries, strict=True):
            got = npy(s, motion, {"X-API-Key": key})
            assert np.abs(got - np.load(tmp_path / "gen" / entry["joints"])).max() < SAME
        # constraints without gradients: met exactly after decoding, not steered (docs/control.md)
        assert info["control"]["steers"] is False
        status, out = s.json("POST", "/v1/generate", {**ask, "num": 1, "path": [[0, 0, 0], [2.5, 1.0, 1.5]]},
                             {"X-API-Key": key})
        assert status == 200 and out["motions"][0]["control"]["path_m"]["max"] < 1e-4, out
        assert "onnx" in s.stderr and "API key required" in s.stderr
    finally:
        assert s.stop() == 0, s.stderr


def test_sigterm_drains_in_flight_requests_and_exits_0(serve_models: Path) -> None:
    """Bound to 0.0.0.0 (a warning on stderr); the server sends itself SIGTERM as its first engine pass starts
    (fault point ``serve.pass``): the request of that pass still gets its motion, then the server exits 0."""
    s = Server("--gan", "gan", "--vae", "vae", cwd=serve_models, host="0.0.0.0",
               env={"LSGAN_FAULT": "serve.pass:SIGTERM"})
    try:
        assert any(line.startswith("warning: listening on 0.0.0.0") and "without a key" in line for line in s.lines)
        status, out = s.json("POST", "/v1/generate", {"text": PROMPT, "frames": 30, "seed": 5})
        code = s.proc.wait(30)
    finally:
        s.stop()
    assert status == 200 and len(out["motions"][0]["joints"]) == 30, out
    assert code == 0, s.stderr
    assert "lsgan serve: stopped" in s.stderr and "Traceback" not in s.stderr
    with pytest.raises(ConnectionRefusedError):
        s.request("GET", "/healthz")


def test_page_is_served_from_the_package(server: Server) -> None:
    from lsgan.serve.files import static_files

    files = static_files()
    if "index.html" not in files:
        pytest.skip("lsgan/serve/static/index.html is not there yet")
    status, head, body = server.request("GET", "/")
    assert status == 200 and head["content-type"].startswith("text/html") and b"<html" in body.lower()
    for name, kind in files.items():
        status, head, body = server.request("GET", f"/static/{name}")
        assert status == 200 and head["content-type"] == kind and len(body) > 0, name
