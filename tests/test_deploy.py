"""ONNX export and the torch-free runtime: ``lsgan export-model --onnx``, ``lsgan generate --runtime onnx`` and the
Python snippet of docs/deploy.md, on a tiny trained pipeline (a text GAN, an action GAN, their VAE)."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from cli_runs import lsgan, snapshot

from lsgan.deploy.int8 import joint_error_mm
from lsgan.deploy.runtime import SPIN_US, load, session_options
from lsgan.generate import Request, generate
from lsgan.threads import usable_cpus

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
PROMPTS = ["a person walks forward", "someone waves the left hand", "a man jumps", "a woman squats down",
           "the figure runs in a circle and then sits on the floor", "kick", "a person turns around twice"]


@pytest.fixture(scope="module")
def runs(serve_models: Path, tmp_path_factory) -> Path:
    """conftest's tiny pipeline and action GAN (hard-linked copies), and their exports made here: gan-onnx (fp32 +
    int8), act-onnx (fp32)."""
    d = tmp_path_factory.mktemp("deploy")
    for name in ("tiny.yaml", "cache.h5", "synth.h5", "vae", "gan", "act-gan"):
        src = serve_models / name
        if src.is_dir():
            shutil.copytree(src, d / name, copy_function=os.link)
        elif src.exists():
            os.link(src, d / name)
    for step in (("export-model", "gan", "--vae", "vae", "-o", "gan-onnx", "--onnx", "--int8"),
                 ("export-model", "act-gan", "--vae", "vae", "-o", "act-onnx", "--onnx")):
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, out.stderr[-3000:]
    return d


def test_export_writes_the_promised_files(runs: Path) -> None:
    from lsgan.models.checkpoint import resolve, weights_hash
    from lsgan.outputs import file_sha256

    m = json.loads((runs / "gan-onnx" / "manifest.json").read_text())
    assert m["format"] == "lsgan-onnx" and m["condition"] == "text" and m["cond_dim"] == 384
    assert (m["noise_dim"], m["latent_dim"], m["fps"], m["max_frames"]) == (8, 16, 20, 200)
    assert len(m["latent_mean"]) == len(m["latent_std"]) == 16 and len(m["feature_std"]) == 263
    assert m["tokenizer"]["max_length"] == 256 and m["tokenizer"]["lowercase"] is True
    assert m["sources"]["vae"]["path"] == str(resolve(runs / "vae").resolve())
    assert m["sources"]["vae"]["weights_hash"] == weights_hash(runs / "vae")
    assert m["sources"]["generator"]["weights_hash"] == weights_hash(runs / "gan")
    assert sorted(m["files"]) == sorted(["text_encoder.onnx", "generator.onnx",
                                         "decoder.onnx", "decoder.int8.onnx", "tokenizer.json", "vocab.txt"])
    for name, entry in m["files"].items():
        assert file_sha256(runs / "gan-onnx" / name) == entry["sha256"], name
    model = load(runs / "gan-onnx")
    for graph, session in model.sessions.items():
        for declared, actual in zip(m["graphs"][graph]["inputs"] + m["graphs"][graph]["outputs"],
                                    session.get_inputs() + session.get_outputs()):
            assert declared["name"] == actual.name
            assert actual.type == f"tensor({'float' if declared['dtype'] == 'float32' else declared['dtype']})"
            assert [d if isinstance(d, int) else None for d in declared["shape"]] == \
                [d if isinstance(d, int) else None for d in actual.shape], graph
    act = json.loads((runs / "act-onnx" / "manifest.json").read_text())
    assert act["condition"] == "action" and act["action_names"] and "text_encoder" not in act["graphs"]
    assert act["graphs"]["generator"]["inputs"][1] == {"name": "condition", "dtype": "int64", "shape": ["batch"]}


@pytest.mark.parametrize("prompts, frames, num", [
    (PROMPTS[:1], [40], 1),  # batch 1, shorter than the 64 frames traced
    (PROMPTS[:3], [120, 196, 64], 2),  # batch 6, one motion longer than traced, mixed lengths in one batch
    (PROMPTS, [150] * 7, 1),  # batch 7, prompts of other token counts than the 9 traced
])
def test_fp32_graphs_give_torchs_features(runs: Path, one_thread, prompts, frames, num) -> None:
    """Same seed, same prompts: the ONNX runtime's features and joints equal lsgan.generate's within 1e-4 (both
    runtimes draw the same noise from a seed)."""
    requests = [Request(text=p, frames=f) for p, f in zip(prompts, frames)]
    ref = generate(runs / "gan", runs / "vae", requests, num=num, seed=3, device="cpu")
    got = load(runs / "gan-onnx", threads=1).generate(requests, num=num, seed=3)
    assert [m.features.shape for m in got.motions] == [m.features.shape for m in ref.motions]
    for a, b in zip(got.motions, ref.motions):
        np.testing.assert_allclose(a.features, b.features, atol=1e-4, rtol=0)
        np.testing.assert_allclose(a.joints, b.joints, atol=1e-4, rtol=0)


def test_text_encoder_graph_gives_minilms_embeddings(runs: Path, one_thread) -> None:
    from lsgan.models.text import load_text_encoder

    model = load(runs / "gan-onnx", threads=1)
    for batch in (PROMPTS[:1], PROMPTS, PROMPTS * 40):  # 280 prompts: two batches of the runtime
        np.testing.assert_allclose(model.embed(batch), load_text_encoder("minilm").encode(batch).numpy(), atol=1e-5)


def test_text_cache_embeds_each_prompt_once_and_gives_the_same_rows(runs: Path) -> None:
    """``load(..., text_cache=N)`` (what lsgan serve --model uses): rows equal the uncached runtime's, a prompt
    held is not embedded again, and the least recently used prompt is dropped first."""
    plain, cached = load(runs / "gan-onnx", threads=1), load(runs / "gan-onnx", threads=1, text_cache=3)
    batch = [PROMPTS[0], PROMPTS[1], PROMPTS[0]]
    np.testing.assert_allclose(cached.embed(batch), plain.embed(batch), atol=1e-6, rtol=0)
    assert (cached.text_cache.hits, cached.text_cache.misses) == (0, 2)
    np.testing.assert_allclose(cached.embed(PROMPTS[:3]), plain.embed(PROMPTS[:3]), atol=1e-6, rtol=0)
    assert (cached.text_cache.hits, cached.text_cache.misses) == (2, 3)
    cached.embed([PROMPTS[3]])  # holds 3: PROMPTS[0], the least recently used, goes
    cached.embed([PROMPTS[0]])
    assert (cached.text_cache.hits, cached.text_cache.misses) == (2, 5)
    assert cached.embed([]).shape == (0, 384)


def test_action_gan_exports_and_matches_torch(runs: Path, one_thread) -> None:
    model = load(runs / "act-onnx", threads=1)
    names = model.manifest["action_names"]
    requests = [Request(action=names[i % len(names)], frames=f) for i, f in enumerate([48, 120, 196])]
    ref = generate(runs / "act-gan", runs / "vae", requests, seed=1, device="cpu")
    got = model.generate(requests, seed=1)
    for a, b in zip(got.motions, ref.motions):
        np.testing.assert_allclose(a.features, b.features, atol=1e-4, rtol=0)


def doc_snippet() -> str:
    """The Python block of docs/deploy.md that follows its deploy-snippet marker, exactly as written there."""
    text = (ROOT / "docs" / "deploy.md").read_text()
    found = re.search(r"<!-- deploy-snippet:[^>]*-->\n```python\n(.*?)```", text, re.S)
    assert found, "docs/deploy.md lost its tested Python snippet"
    return found.group(1)


NO_TORCH = textwrap.dedent('''
    import sys
    from importlib.abc import MetaPathFinder

    class NoTorch(MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ImportError(f"{name} is blocked: this code must run without torch")

    sys.meta_path.insert(0, NoTorch())
''')


def test_runtime_and_doc_snippet_run_without_torch(runs: Path, tmp_path: Path) -> None:
    """docs/deploy.md's snippet, lsgan's runtime and `lsgan generate --runtime onnx` with torch unimportable."""
    (tmp_path / "gan-onnx").symlink_to(runs / "gan-onnx")  # the folder name the snippet uses
    script = NO_TORCH + textwrap.dedent(f'''
        import numpy as np
        namespace = {{}}
        exec(compile({doc_snippet()!r}, "docs/deploy.md", "exec"), namespace)
        from lsgan.deploy.runtime import SPIN_US, load, session_options
        from lsgan.generation import Request
        motions = load("gan-onnx").generate([Request(text="a person walks forward", frames=120)], seed=0).motions
        from lsgan.cli import main
        try:
            main(["generate", "--runtime", "onnx", "--gan", "gan-onnx", "--text", "a person walks forward",
                  "--frames", "120", "-o", "out"])
        except SystemExit as e:
            assert e.code == 0, e.code
        assert not [m for m in sys.modules if m == "torch" or m.startswith("torch.")]
        np.savez("result.npz", snippet=namespace["features"], snippet_joints=namespace["joints"],
                 runtime=motions[0].features, runtime_joints=motions[0].joints)
    ''')
    out = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    result = np.load(tmp_path / "result.npz")
    expected = load(runs / "gan-onnx").generate([Request(text="a person walks forward", frames=120)], seed=0).motions[0]
    assert result["snippet"].shape == (1, 120, 263) and result["snippet_joints"].shape == (1, 120, 22, 3)
    assert np.isfinite(result["snippet"]).all() and np.isfinite(result["snippet_joints"]).all()
    np.testing.assert_allclose(result["snippet"][0], expected.features, atol=1e-5, rtol=0)
    np.testing.assert_allclose(result["snippet_joints"][0], expected.joints, atol=1e-5, rtol=0)
    np.testing.assert_allclose(result["runtime"], expected.features, atol=1e-5, rtol=0)
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    np.testing.assert_allclose(np.load(tmp_path / "out" / manifest["motions"][0]["features"]), expected.features,
                               atol=1e-5, rtol=0)


def test_generate_runtime_onnx_is_deterministic(runs: Path, tmp_path: Path) -> None:
    args = ["generate", "--runtime", "onnx", "--gan", runs / "gan-onnx", "--text", PROMPTS[0], "--text", PROMPTS[1],
            "--frames", 48, "--num", 2]
    runs_ = (("a", ["--seed", 7]), ("b", ["--seed", 7]), ("c", ["--seed", 8]), ("q", ["--seed", 7, "--int8"]))
    for name, extra in runs_:
        out = lsgan(*args, *extra, "-o", tmp_path / name, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        assert "ms per motion" in out.stderr
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["runtime"]["name"] == "onnx" and manifest["runtime"]["variant"] == "fp32"
    assert manifest["runtime"]["dir"] == str((runs / "gan-onnx").resolve()) and manifest["seed"] == 7
    assert json.loads((tmp_path / "q" / "manifest.json").read_text())["runtime"]["variant"] == "int8"
    assert manifest["gan"]["sha256"] == json.loads((runs / "gan-onnx" / "manifest.json").read_text())[
        "sources"]["generator"]["weights_hash"]
    files = sorted(p.name for p in (tmp_path / "a").glob("*.npy"))
    assert len(files) == 8
    for name in files:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert not np.array_equal(np.load(tmp_path / "a" / files[0]), np.load(tmp_path / "c" / files[0]))


def test_one_seed_gives_one_motion_in_both_runtimes(runs: Path, tmp_path: Path) -> None:
    """``lsgan generate --seed 7`` under torch and under ``--runtime onnx`` (fp32): the same features within 1e-4 and
    the same rigid joints, for every motion."""
    args = ["--text", PROMPTS[0], "--text", PROMPTS[4], "--frames", 64, "--num", 3, "--seed", 7]
    for name, runtime in (("torch", ["--gan", runs / "gan", "--vae", runs / "vae"]),
                          ("onnx", ["--runtime", "onnx", "--gan", runs / "gan-onnx"])):
        out = lsgan("generate", *runtime, *args, "-o", tmp_path / name, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
    entries = json.loads((tmp_path / "torch" / "manifest.json").read_text())["motions"]
    assert len(entries) == 6
    for e in entries:
        for kind in ("features", "joints"):
            a, b = (np.load(tmp_path / name / e[kind]) for name in ("torch", "onnx"))
            np.testing.assert_allclose(b, a, atol=1e-4, rtol=0, err_msg=f"{e[kind]}")


def test_onnx_route_meets_constraints_as_torch_does_without_steering(runs: Path, tmp_path: Path) -> None:
    """``generate --runtime onnx --path --keyframe``: the path met to float precision and the manifest saying the
    motions were not steered; the joints equal the torch runtime's with its optimisation off (0 steps), so both
    meet constraints by one implementation (lsgan.constraints.meet, place_measured)."""
    from lsgan.constraints import Constraints, read_keyframe, read_path
    from lsgan.control import ControlSettings

    (tmp_path / "path.csv").write_text("t,x,z\n0,0,0\n1.5,0.8,1.2\n2.35,1.0,2.0\n")
    (tmp_path / "hand.json").write_text(json.dumps({"right_wrist": [0.6, 1.0, 1.3]}))
    out = lsgan("generate", "--runtime", "onnx", "--gan", runs / "gan-onnx", "--text", PROMPTS[0], "--frames", 48,
                "--num", 2, "--seed", 3, "--path", tmp_path / "path.csv", "--keyframe", f"30:{tmp_path / 'hand.json'}",
                "-o", tmp_path / "onnx", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "root path: missed by 0.00 cm" in out.stderr
    manifest = json.loads((tmp_path / "onnx" / "manifest.json").read_text())
    assert manifest["control"]["steered"] is False and manifest["control"]["path"][0] == [0, 0.0, 0.0]
    c = Constraints(48, path=read_path(tmp_path / "path.csv", 48),
                    keyframes=dict([read_keyframe(f"30:{tmp_path / 'hand.json'}", 48)]))
    ref = generate(runs / "gan", runs / "vae", [Request(text=PROMPTS[0], frames=48)], num=2, seed=3, constraints=c,
                   control_settings=ControlSettings(noise_steps=0))
    for entry, motion in zip(manifest["motions"], ref.motions, strict=True):
        assert entry["control"]["path_m"]["max"] < 1e-4
        np.testing.assert_allclose(np.load(tmp_path / "onnx" / entry["joints"]), motion.joints, atol=1e-4, rtol=0)


@pytest.mark.parametrize("threads, spin_us, spinning", [(1, SPIN_US, "0"), (2, SPIN_US, "1"), (2, 0, "0")])
def test_only_a_pool_spin_waits_and_only_briefly(threads: int, spin_us: int, spinning: str) -> None:
    opts = session_options(threads, spin_us)
    assert opts.intra_op_num_threads == threads
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == spinning
    if spinning == "1":
        assert opts.get_session_config_entry("session.intra_op.spin_duration_us") == str(SPIN_US)


@pytest.mark.skipif(not sys.platform.startswith("linux") or usable_cpus() < 2,
                    reason="the load is read from /proc; one usable core never spin-waits")
def test_sessions_stop_spinning_beside_busy_processes_with_the_same_motions(runs: Path, monkeypatch) -> None:
    """Busy processes on every core after loading: the next pass (past the half-second window) runs in sessions
    that sleep instead of spinning, on every core still, and makes the same bits as before; one thread never spins."""
    monkeypatch.delenv("LSGAN_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    requests = [Request(text=p, frames=48) for p in PROMPTS[:3]]
    model, single = load(runs / "gan-onnx", variant="int8"), load(runs / "gan-onnx", variant="int8", threads=1)
    expected = model.generate(requests, num=2, seed=3).motions
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(usable_cpus())]
    try:
        time.sleep(0.8)
        busy = model.generate(requests, num=2, seed=3)
        alone = single.generate(requests, num=2, seed=3)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
    assert not model.spinning and False in model._sets
    assert model.threads == busy.runtime["threads"] == usable_cpus()
    assert not single.spinning and list(single._sets) == [False]
    for a, b, c in zip(busy.motions, expected, alone.motions):
        assert np.array_equal(a.features, b.features) and np.array_equal(c.features, b.features)


def test_int8_error_is_recorded_and_reproduced(runs: Path) -> None:
    """The manifest's int8 joint error is what the graphs give (recomputed here), and physically small."""
    m = json.loads((runs / "gan-onnx" / "manifest.json").read_text())
    int8 = m["variants"]["int8"]
    assert int8["quantisation"]["graphs"] == ["decoder"]
    assert int8["graphs"]["generator"] == "generator.onnx"  # the generator stays fp32
    err = int8["joint_error_mm"]
    assert err["motions"] == 100 and 0 < err["mean"] <= err["max"]
    assert err["mean"] < 50, "int8 moved the joints by more than 5 cm on average"
    again = joint_error_mm(load(runs / "gan-onnx"), load(runs / "gan-onnx", variant="int8"))
    assert again["mean"] == pytest.approx(err["mean"], rel=1e-4) and again["max"] == pytest.approx(err["max"], rel=1e-4)
    assert int8["graphs"]["text_encoder"] == "text_encoder.onnx"  # so does the text encoder
    size = {name: (runs / "gan-onnx" / name).stat().st_size for name in ("decoder.onnx", "decoder.int8.onnx")}
    assert size["decoder.int8.onnx"] < size["decoder.onnx"]  # int8 matrices (the tiny model is mostly other tensors)


def test_int8_quantises_the_feed_forward_and_self_attention_products_only(runs: Path) -> None:
    """Four int8 products per decoder layer (d -> ff, ff -> d, the self-attention's in and out projections), per
    channel; every other product stays fp32."""
    import onnx

    m = json.loads((runs / "gan-onnx" / "manifest.json").read_text())
    cfg = json.loads((runs / "vae" / "best" / "config.json").read_text())["config"]["model"]
    nodes = m["variants"]["int8"]["quantisation"]["quantised_nodes"]
    assert len(nodes) == 4 * cfg["num_layers"]
    graph = onnx.load(str(runs / "gan-onnx" / "decoder.int8.onnx")).graph
    integer = [n for n in graph.node if n.op_type in ("MatMulInteger", "DynamicQuantizeMatMul")]
    assert len(integer) == len(nodes)
    fp32 = onnx.load(str(runs / "gan-onnx" / "decoder.onnx")).graph
    products = [n for n in fp32.node if n.op_type in ("MatMul", "Gemm")]
    assert len(products) > len(nodes)  # cross-attention, skip and output products were left in fp32
    scales = {i.name: tuple(i.dims) for i in graph.initializer if i.name.endswith("_scale")}
    assert any(dims and dims[0] > 1 for dims in scales.values())  # per-channel weight scales


def test_force_replaces_only_lsgans_files(runs: Path, tmp_path: Path) -> None:
    """Exporting again with --force replaces the earlier export (the module's, hard-linked: replaced, never edited in
    place) and keeps the user's own file beside it."""
    args = ["export-model", runs / "act-gan", "--vae", runs / "vae", "-o", tmp_path / "act", "--onnx"]
    before = snapshot(runs / "act-onnx")
    linked_copy(runs / "act-onnx", tmp_path / "act")
    (tmp_path / "act" / "notes.txt").write_text("mine")
    again = lsgan(*args, cwd=tmp_path)
    assert again.returncode == 1 and "pass --force" in again.stderr
    again = lsgan(*args, "--force", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "act" / "notes.txt").read_text() == "mine"
    assert load(tmp_path / "act").generate([Request(action="walk", frames=40)]).motions[0].joints.shape == (40, 22, 3)
    assert snapshot(runs / "act-onnx") == before


def test_only_gans_export(tmp_path: Path) -> None:
    """A latent-diffusion run is refused with the reason, before anything is written."""
    from lsgan.deploy.onnx_export import export_onnx

    (tmp_path / "diffusion").mkdir()
    (tmp_path / "diffusion" / "config.json").write_text(json.dumps({"kind": "diffusion", "config": {}}))
    with pytest.raises(ValueError, match="only GANs export to ONNX"):
        export_onnx(tmp_path / "diffusion", tmp_path / "out")
    assert not (tmp_path / "out").exists()


# ---- bad input, in tests/test_bad_input.py's style ------------------------------------------------------------


def linked_copy(src: Path, dst: Path) -> Path:
    """A copy of an export whose files are hard links (a changed file must be replaced, not edited in place)."""
    shutil.copytree(src, dst, copy_function=os.link)
    return dst


def corrupt_graph(w: Path, runs: Path) -> Path:
    d = linked_copy(runs / "gan-onnx", w / "gan-onnx")
    data = (d / "decoder.onnx").read_bytes()
    (d / "decoder.onnx").unlink()
    (d / "decoder.onnx").write_bytes(data[: len(data) // 2])
    return d


def future_format(w: Path, runs: Path) -> Path:
    d = linked_copy(runs / "gan-onnx", w / "gan-onnx")
    m = json.loads((d / "manifest.json").read_text())
    (d / "manifest.json").unlink()
    (d / "manifest.json").write_text(json.dumps({**m, "format_version": 99}))
    return d


def onnx_args(gan: Path, w: Path, *extra) -> list:
    return ["generate", "--runtime", "onnx", "--gan", gan, "--text", "a person walks", "-o", w / "out", *extra]


BAD = [
    ("no-manifest", lambda w, r: onnx_args(r / "gan", w), 1, "no manifest.json"),
    ("corrupt-graph", lambda w, r: onnx_args(corrupt_graph(w, r), w), 1, "decoder.onnx: changed since it was exported"),
    ("format-version", lambda w, r: onnx_args(future_format(w, r), w), 1, "format version 99"),
    ("int8-not-exported", lambda w, r: ["generate", "--runtime", "onnx", "--int8", "--gan", r / "act-onnx",
                                        "--action", "walk", "-o", w / "out"], 1, "export with --int8"),
    ("too-many-frames", lambda w, r: onnx_args(r / "gan-onnx", w, "--frames", 500), 1, "1 to 200 frames"),
    ("action-for-text-model", lambda w, r: ["generate", "--runtime", "onnx", "--gan", r / "gan-onnx", "--action",
                                            "walk", "-o", w / "out"], 1, "conditioned on text"),
    ("vae-with-onnx", lambda w, r: onnx_args(r / "gan-onnx", w, "--vae", r / "vae"), 2, "--vae"),
    ("int8-with-torch", lambda w, r: ["generate", "--gan", r / "gan", "--vae", r / "vae", "--text", "x", "--int8",
                                      "-o", w / "out"], 2, "--runtime onnx"),
]


@pytest.mark.parametrize("args, code, phrase", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_onnx_input(args, code: int, phrase: str, runs: Path, tmp_path: Path) -> None:
    """Exit code, one `error:` line holding the phrase, no traceback, no existing file changed."""
    w = tmp_path / "w"
    w.mkdir()
    argv = args(w, runs)
    before = snapshot(w, runs / "gan-onnx", runs / "act-onnx")
    out = lsgan(*argv, cwd=w)
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert out.returncode == code, out.stderr
    assert len(errors) == 1 and phrase.lower() in errors[0].lower(), out.stderr
    assert "Traceback" not in out.stderr
    after = snapshot(w, runs / "gan-onnx", runs / "act-onnx")
    assert not [str(p) for p, h in before.items() if after.get(p) != h], "pre-existing files changed or removed"
    assert not (w / "out").exists() or not any((w / "out").iterdir())
