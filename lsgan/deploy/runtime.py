"""Motions from an ONNX export with onnxruntime, tokenizers and numpy: no torch anywhere.

The pipeline is the torch one (:func:`lsgan.generate.generate`) step by step: tokenise (the export's
tokenizer.json: lowercase WordPiece, truncated at its max length, padded to the longest prompt of a batch),
text encoder (mean-pooled, L2-normalised embedding), generator (noise ~ N(0, 1), standardised latent),
de-standardise (latent * std + mean), decoder (with a mask of the real frames), de-normalise
(features * Std + Mean), joints by the HumanML3D recovery made rigid (:mod:`lsgan.motion.rigid`). The noise is
the same draw as torch's (:func:`lsgan.generation.draw_noise`), so one seed gives one motion in both runtimes.

Sessions run one intra-op thread per usable core (``threads=``, ``LSGAN_THREADS`` or ``OMP_NUM_THREADS`` fix
another count), and their threads spin-wait between operations, for at most :data:`SPIN_US`, only while other
processes leave every core free (:class:`lsgan.threads.FreeCores`, re-measured at most every half second): sleeping
and waking at each of a pass's ~550 operations cost the paper-sized int8 decoder a quarter of its time at batch 1 on
the idle machine, but spinning threads collapse beside a busy process (the decoder at batch 1 beside one busy loop:
18.4 ms spinning, 11.4 sleeping). One set of sessions spins and one sleeps, each made when first needed (their
outputs are the same bits, tested). Beside busy processes, all cores without spinning did as well as one thread at
batch 1 (17.3 and 15.8 ms beside one, 29.8 and 32.2 beside three) and better at 256 motions (5.9 against 7.7 s
beside three): ``benchmarks/contention.py``.
"""
from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lsgan.deploy.manifest import GRAPHS, read_manifest, variant_files, verify
from lsgan.generation import (CPU_DECODE_FRAMES, Generation, Request, check_prompts, decode_batches, decoded_motion,
                              draw_noise, place_measured)
from lsgan.textcache import PromptCache
from lsgan.threads import FreeCores, fixed_threads, usable_cpus


def _ort():
    try:
        import onnxruntime
    except ImportError as e:
        raise RuntimeError("the ONNX runtime needs onnxruntime: pip install onnxruntime (or 'lsgan[onnx]')") from e
    return onnxruntime


def default_threads() -> int:
    """A count the user fixed (``LSGAN_THREADS``, what ``lsgan --threads N`` sets, else ``OMP_NUM_THREADS``), else
    every usable core."""
    return fixed_threads() or usable_cpus()


# How long a pool's idle threads spin before they sleep (onnxruntime >= 1.26; older ones ignore the key). The
# paper-sized int8 decoder at batch 1, 2 threads, idle 2-core AMD EPYC: 9.0 ms sleeping, 6.9 spinning up to 50-200 us,
# 7.0 spinning without a bound; the text encoder, generator and decoder in a row: 15.8 ms sleeping, 10.5 at 50 us,
# 13.9 at 1,000 us and about twice 15.8 unbounded (each session's pool spins on through the next session's pass).
SPIN_US = 50


def session_options(threads: int | None = None, spin_us: int = SPIN_US):
    """onnxruntime options: ``threads`` intra-op threads (default: :func:`default_threads`); with two or more, idle
    threads spin-wait up to ``spin_us`` microseconds before they sleep (0: they sleep at once)."""
    opts = _ort().SessionOptions()
    opts.intra_op_num_threads = threads or default_threads()
    opts.inter_op_num_threads = 1
    spinning = opts.intra_op_num_threads > 1 and spin_us > 0
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    if spinning:
        opts.add_session_config_entry("session.intra_op.spin_duration_us", str(int(spin_us)))
    opts.log_severity_level = 3  # errors only: its warnings about unused initialisers are noise here
    return opts


# onnxruntime's CPU kernel for the SkipLayerNormalization it fuses from Add + LayerNormalization took 95 us on a
# (1, 120, 256) tensor where the two ops it replaces took ~40 (onnxruntime 1.32, 2-core AMD EPYC): left unfused,
# the paper-sized int8 decoder runs ~9% faster at batch 1 and MiniLM ~6% at 8 prompts, with the same values to
# float rounding (1.6e-6 in the fp32 decoder's features).
UNFUSED = ["SkipLayerNormFusion"]


def open_session(path: Path, options):
    """An inference session on the CPU; a file onnxruntime cannot load is named in a ValueError."""
    ort = _ort()
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"],
                                    disabled_optimizers=UNFUSED)
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own types for damaged graphs
        detail = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{path}: onnxruntime cannot load it ({detail[:300]})") from None


class OnnxMotionModel:
    """An exported folder with its sessions open: ``generate(requests)`` -> :class:`Generation`."""

    def __init__(self, folder: str | os.PathLike, manifest: dict, *, variant: str = "fp32",
                 threads: int | None = None, spin_us: int = SPIN_US, check_files: bool = True,
                 text_cache: int = 0) -> None:
        self.folder, self.manifest, self.variant = Path(folder), manifest, variant
        self.text_cache = PromptCache(text_cache) if text_cache > 0 else None  # prompt embeddings kept
        files = variant_files(self.folder, manifest, variant)
        tokenizer = manifest.get("tokenizer")
        if check_files:
            used = [files[g] for g in GRAPHS if g in files] + ([tokenizer["file"]] if tokenizer else [])
            verify(self.folder, manifest, used)
        self._files = {g: self.folder / files[g] for g in GRAPHS if g in files}
        self._spin_us = spin_us
        self.threads = threads or default_threads()
        self._load = FreeCores() if self.threads > 1 and spin_us > 0 else None  # None: never spins
        self.spinning = False  # whether the latest pass's sessions spin-wait
        self._sets: dict[bool, dict] = {}  # spin-waiting or not -> the sessions
        self._sessions()
        self.tokenizer = _tokenizer(self.folder, tokenizer) if manifest["condition"] == "text" else None
        f32 = lambda key: np.asarray(manifest[key], np.float32)  # noqa: E731
        self.latent_mean, self.latent_std = f32("latent_mean"), f32("latent_std")  # (Z,)
        self.feature_mean, self.feature_std = f32("feature_mean"), f32("feature_std")  # (263,)

    def _sessions(self) -> dict:
        """The sessions for a pass starting now: spinning ones while other processes leave every core free."""
        self.spinning = self._load is not None and self._load.threads() in (None, self._load.cpus)
        if self.spinning not in self._sets:
            opts = session_options(self.threads, self._spin_us if self.spinning else 0)
            self._sets[self.spinning] = {g: open_session(f, opts) for g, f in self._files.items()}
        self.sessions = self._sets[self.spinning]
        return self.sessions

    @property
    def max_frames(self) -> int:
        return int(self.manifest["max_frames"])

    def embed(self, texts: Sequence[str], batch_size: int = 256) -> np.ndarray:
        """Sentence embeddings (N, D) float32 of ``texts``, as MiniLMEncoder.encode gives them (those of the
        prompts the text cache holds from there)."""
        if self.text_cache is None or not texts:
            return self._embed(texts, batch_size)
        return np.stack(self.text_cache.rows(texts, lambda missing: self._embed(missing, batch_size)))

    def _embed(self, texts: Sequence[str], batch_size: int) -> np.ndarray:
        unique = list(dict.fromkeys(texts))
        rows = []
        for b in range(0, len(unique), batch_size):
            enc = self.tokenizer.encode_batch(unique[b:b + batch_size])
            ids = np.array([e.ids for e in enc], np.int64)  # (B, L)
            mask = np.array([e.attention_mask for e in enc], np.int64)  # (B, L)
            feed = {"input_ids": ids, "attention_mask": mask}
            rows.append(self._sessions()["text_encoder"].run(["embedding"], feed)[0])
        table = np.concatenate(rows) if rows else np.zeros((0, self.manifest["cond_dim"]), np.float32)
        index = {t: i for i, t in enumerate(unique)}
        return table[[index[t] for t in texts]]

    def conditions(self, requests: list[Request], batch_size: int = 256) -> np.ndarray:
        """The generator's condition per request: embeddings (R, D) float32, or action indices (R,) int64."""
        if self.manifest["condition"] == "text":
            if any(r.text is None for r in requests):
                raise ValueError(f"{self.folder} is conditioned on text: give prompts (--text or --prompts), "
                                 "not --action")
            return self.embed([r.text for r in requests], batch_size)
        names = self.manifest.get("action_names", [])
        unknown = sorted({str(r.action) for r in requests if r.action not in names})
        if unknown:
            raise ValueError(f"unknown action(s) {unknown}; this model knows {names}")
        return np.array([names.index(r.action) for r in requests], np.int64)

    def latents(self, noise: np.ndarray, cond: np.ndarray, batch_size: int = 256) -> np.ndarray:
        """Latents (N, Z) in the VAE's space: the generator's standardised output * std + mean."""
        run = self._sessions()["generator"].run
        z = [run(["latent"], {"noise": noise[b:b + batch_size], "condition": cond[b:b + batch_size]})[0]
             for b in range(0, len(noise), batch_size)]
        return np.concatenate(z) * self.latent_std + self.latent_mean

    def check_frames(self, frames: list[int]) -> None:
        """Refuse lengths beyond the decoder's positional table, before any graph runs."""
        bad = sorted({f for f in frames if not 1 <= f <= self.max_frames})
        if bad:
            raise ValueError(f"{bad[-1]} frames asked; this export decodes 1 to {self.max_frames} frames (the VAE's "
                             "positional table)")

    def decode(self, z: np.ndarray, frames: list[int], batch_size: int = 256) -> list[np.ndarray]:
        """De-normalised features (T_i, 263) per latent; batches of similar lengths within the CPU's frame budget
        (:func:`lsgan.generation.decode_batches`), padded frames masked."""
        self.check_frames(frames)
        out: list[np.ndarray] = [None] * len(frames)  # type: ignore[list-item]
        for idx in decode_batches(frames, batch_size, CPU_DECODE_FRAMES):
            lengths = np.array([frames[i] for i in idx])
            mask = np.arange(lengths.max())[None] < lengths[:, None]  # (B, T)
            x = self._sessions()["decoder"].run(["features"], {"latent": z[idx], "mask": mask})[0]  # (B, T, 263)
            for j, i in enumerate(idx):
                out[i] = x[j, :frames[i]] * self.feature_std + self.feature_mean
        return out

    def generate(self, requests: list[Request], *, num: int = 1, seed: int = 0, noise: np.ndarray | None = None,
                 batch_size: int = 256, fix_feet: bool = False, constraints=None, placement=None) -> Generation:
        """``num`` motions per request; ``noise`` (len(requests)*num, noise_dim) replaces the seeded draw;
        ``fix_feet`` as in :func:`lsgan.generation.decoded_motion`. ``constraints`` (every motion's, in its own
        frame) are met after decoding, without the torch runtime's optimisation first (onnxruntime has no
        gradients: docs/control.md); ``placement`` then moves the motions (a continuation's)."""
        from lsgan.constraints import check_reach, meet

        check_prompts(requests)
        n = len(requests) * num
        if n == 0:
            raise ValueError("nothing to generate: no requests (or num=0)")
        if noise is None:
            noise = draw_noise(seed, n, int(self.manifest["noise_dim"]))
        if constraints is not None:
            if any(r.frames != constraints.frames for r in requests):
                raise ValueError(f"the constraints are for {constraints.frames} frames, the motions have "
                                 f"{sorted({r.frames for r in requests})}")
            check_reach(constraints, *self.reach())
        feats, timings = self.features([r for r in requests for _ in range(num)], noise, batch_size)
        if constraints is not None:
            t0 = time.perf_counter()
            feats = [meet(f, constraints) for f in feats]
            timings["control"] = time.perf_counter() - t0
        motions = [decoded_motion(requests[k // num], k % num, f, fix_feet) for k, f in enumerate(feats)]
        if constraints is not None:
            place_measured(motions, [constraints] * n, placement)
        control = None if constraints is None else {
            **constraints.describe(), "steered": False,
            **({"placement": placement.describe()} if placement is not None else {})}
        return Generation(motions=motions, timings_s=timings, seed=seed, fix_feet=fix_feet, control=control,
                          **self._provenance())

    def reach(self) -> tuple[float, np.ndarray]:
        """What constraints are held to (:func:`lsgan.constraints.model_reach` of the export's feature statistics)."""
        from lsgan.constraints import model_reach

        return model_reach(self.feature_mean, self.feature_std)

    def features(self, requests: list[Request], noise: np.ndarray, batch_size: int = 256) -> tuple[list, dict]:
        """De-normalised features (T, 263) of one motion per request from its row of ``noise``, and the timings
        (s) of text encoding, generator and decoder."""
        n, frames = len(requests), [r.frames for r in requests]
        self.check_frames(frames)
        if noise.shape != (n, self.manifest["noise_dim"]):
            raise ValueError(f"noise of shape {noise.shape}; expected ({n}, {self.manifest['noise_dim']})")
        timings = {"text_encoding": 0.0, "generator": 0.0, "vae_decoding": 0.0}
        t0 = time.perf_counter()
        cond = self.conditions(requests, batch_size)
        if self.manifest["condition"] == "text":
            timings["text_encoding"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        z = self.latents(noise.astype(np.float32), cond, batch_size)
        timings["generator"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        feats = self.decode(z, frames, batch_size)
        timings["vae_decoding"] = time.perf_counter() - t0
        return feats, timings

    def _provenance(self) -> dict:
        """Generation's fields that say where the motions came from: the source checkpoints and this export."""
        src = self.manifest["sources"]
        files = variant_files(self.folder, self.manifest, self.variant)
        return {
            "gan": src["generator"]["path"], "vae": src["vae"]["path"], "kind": "gan",
            "checkpoints": {k: {"path": src[k]["path"], "sha256": src[k]["weights_hash"]}
                            for k in ("generator", "vae")},
            "runtime": {"name": "onnx", "dir": str(self.folder.resolve()), "variant": self.variant,
                        "threads": self.threads, "graphs": files,
                        "format_version": self.manifest["format_version"]},
        }


def _tokenizer(folder: Path, settings: dict):
    """The export's tokenizer with its recorded truncation and padding (whatever the file itself says)."""
    from tokenizers import Tokenizer

    tok = Tokenizer.from_file(str(folder / settings["file"]))
    tok.enable_truncation(max_length=int(settings["max_length"]))
    tok.enable_padding(pad_id=int(settings["pad_id"]), pad_token=settings["pad_token"])  # to the longest in a batch
    return tok


def load(folder: str | os.PathLike, *, variant: str = "fp32", threads: int | None = None, spin_us: int = SPIN_US,
         text_cache: int = 0) -> OnnxMotionModel:
    """Open an exported folder (checked: format version, the SHA-256 of every file this variant uses);
    ``threads``: intra-op threads (default: :func:`default_threads`); ``spin_us``: how long idle threads
    spin-wait while the machine is otherwise idle (0: never); ``text_cache``: prompt embeddings kept across calls (0:
    none)."""
    return OnnxMotionModel(folder, read_manifest(folder), variant=variant, threads=threads, spin_us=spin_us,
                           text_cache=text_cache)


def generate_onnx(folder: str | os.PathLike, requests: list[Request], *, num: int = 1, seed: int = 0,
                  noise: np.ndarray | None = None, variant: str = "fp32", threads: int | None = None,
                  batch_size: int = 256, fix_feet: bool = False, constraints=None, placement=None) -> Generation:
    """``lsgan generate --runtime onnx``: :func:`load` then :meth:`OnnxMotionModel.generate`."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    return load(folder, variant=variant, threads=threads).generate(
        requests, num=num, seed=seed, noise=noise, batch_size=batch_size, fix_feet=fix_feet, constraints=constraints,
        placement=placement)


def generate_timeline_onnx(folder: str | os.PathLike, segments: list, *, overlap: int, source: str | None = None,
                           int8: bool = False, seed: int = 0, batch_size: int = 256,
                           fix_feet: bool = False) -> Generation:
    """:func:`lsgan.timeline.generate_timeline` on an ONNX export's folder: the same segments, seams and seed."""
    from lsgan.timeline import timeline_motion

    model = load(folder, variant="int8" if int8 else "fp32")
    return timeline_motion(segments, overlap, lambda r: model.generate(r, seed=seed, batch_size=batch_size,
                                                                          fix_feet=fix_feet), model.max_frames, source)
