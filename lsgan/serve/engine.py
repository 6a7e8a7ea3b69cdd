"""The models of ``lsgan serve``, loaded once, behind one small interface: ``engine.run(items)``.

Two backends: :class:`TorchEngine` (a GAN and its VAE, the pass of :func:`lsgan.generate.run_models`) and
:class:`OnnxEngine` (an ``export-model`` folder, :class:`lsgan.deploy.runtime.OnnxMotionModel`). Each item of a
pass draws its noise from its own seed exactly as ``lsgan generate --seed SEED --num NUM`` draws it for that one
request (:func:`lsgan.generation.draw_noise`, the same in both backends), so a motion does not depend on what it was
batched with; its joints are made rigid as ``generate``'s are (:func:`lsgan.generation.decoded_motion`).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from lsgan.data.skeleton import FPS
from lsgan.generation import Request, decoded_motion, draw_noise, place_measured


@dataclass(frozen=True)
class Item:
    """One request of a pass: a prompt or an action label, its length, how many motions, and their seed; what they
    must do (:meth:`lsgan.constraints.Constraints.record`, in their own frame) and where they then stand
    (a :class:`lsgan.constraints.Placement`'s yaw, x, z)."""

    text: str | None = None
    action: str | None = None
    frames: int = 120
    num: int = 1
    seed: int = 0
    control: dict | None = None
    placement: tuple[float, float, float] | None = None

    @property
    def request(self) -> Request:
        return Request(text=self.text, action=self.action, frames=self.frames)


@dataclass
class Result:
    """An item's motions (``num`` joint arrays (T, 22, 3) float32, metres) and the pass that made them; with
    constraints, how far each motion is from them (:func:`lsgan.constraints.measure`)."""

    joints: list[np.ndarray]
    timings_ms: dict[str, float] = field(default_factory=dict)  # the pass's: text, generator, decoder, control
    batch_size: int = 1  # motions in the pass
    control: list[dict] | None = None


def _ms(timings_s: dict[str, float]) -> dict[str, float]:
    return {"text": 1e3 * timings_s.get("text_encoding", 0.0), "generator": 1e3 * timings_s.get("generator", 0.0),
            "decoder": 1e3 * timings_s.get("vae_decoding", 0.0), "control": 1e3 * timings_s.get("control", 0.0)}


def _results(items: list[Item], joints: list[np.ndarray], timings_s: dict[str, float]) -> list[Result]:
    """Split a pass's motions (items' motions in order) back into one Result per item."""
    out, k, n = [], 0, len(joints)
    for it in items:
        out.append(Result(joints=joints[k:k + it.num], timings_ms=_ms(timings_s), batch_size=n))
        k += it.num
    return out


def _constrained(item: Item, features: list[np.ndarray], c, timings_s: dict[str, float]) -> Result:
    """The Result of a constrained item from its motions' features, already optimised towards ``c`` where the
    backend can: each met exactly (:func:`lsgan.constraints.meet`), made rigid, measured, then placed."""
    from lsgan.constraints import Placement, meet

    t0 = time.perf_counter()
    motions = [decoded_motion(item.request, 0, meet(f, c)) for f in features]
    place_measured(motions, [c] * len(motions), Placement(*item.placement) if item.placement is not None else None)
    timings_s = {**timings_s, "control": timings_s.get("control", 0.0) + time.perf_counter() - t0}
    return Result(joints=[m.joints for m in motions], timings_ms=_ms(timings_s), batch_size=len(motions),
                  control=[m.control for m in motions])


def _split(items: list[Item]) -> tuple[list[int], list[int]]:
    """Indices of the items without constraints (one pass) and with them (a pass each)."""
    plain = [i for i, it in enumerate(items) if it.control is None]
    return plain, [i for i, it in enumerate(items) if it.control is not None]


class Engine:
    """What the server needs of a model: its condition, actions and frame bound, and ``run(items)``."""

    backend = ""
    device = "cpu"  # where it computes (torch's device)
    condition = "text"  # or "action"
    actions: list[str] = []
    fps: float = float(FPS)
    max_frames: int = 196
    load_s = 0.0  # seconds to load and warm up
    reach: dict | None = None  # what constraints are held to: {"speed": m/s, "skeleton": 22 bone lengths (m)}
    steers = False  # whether constraints are approached by optimisation before they are met (torch) or only met

    def run(self, items: list[Item], *, threads: int | None = None) -> list[Result]:
        """One pass over ``items``; ``threads``: intra-op threads for it where the backend can change them per
        pass (torch; None: the engine's own policy)."""
        raise NotImplementedError

    def close(self) -> None:
        """Let go of what the engine holds (a child process: :class:`lsgan.serve.worker.EngineProcess`)."""

    def describe(self) -> str:
        return f"{self.backend}, {self.condition}-conditioned, up to {self.max_frames} frames"


class TorchEngine(Engine):
    """A latent GAN and its VAE (``--gan RUN --vae RUN``)."""

    backend = "torch"
    steers = True

    def __init__(self, gan: str | os.PathLike, vae: str | os.PathLike, *, device: str = "auto",
                 text_encoder_path: str | None = None, batch_size: int = 256, text_cache: int = 1024) -> None:
        from lsgan.generate import load_models
        from lsgan.textcache import CachedTextEncoder

        self.loaded = load_models(gan, vae, device=device, text_encoder_path=text_encoder_path)
        if self.loaded.encoder is not None and text_cache > 0:
            self.loaded.encoder = CachedTextEncoder(self.loaded.encoder, text_cache)
        if self.loaded.meta["kind"] != "gan":
            raise ValueError(f"{gan}: lsgan serve runs latent GANs; this is a {self.loaded.meta['kind']} checkpoint")
        cfg = self.loaded.model.config
        self.condition = cfg.cond
        self.actions = list(self.loaded.meta.get("extra", {}).get("action_names", [])) if cfg.cond == "action" else []
        self.max_frames = self.loaded.max_frames
        self.batch_size = batch_size
        self.device = str(self.loaded.device)
        import torch

        from lsgan.threads import ThreadPolicy

        # one policy for the server's life, re-measuring every 0.5 s the cores other processes leave free (a fresh
        # one per pass would judge by the runnable tasks of one instant); on a GPU, torch's own count
        self.threads = ThreadPolicy(threads=None if self.loaded.device.type == "cpu" else torch.get_num_threads())
        self._fixed: dict[int, ThreadPolicy] = {}  # a pass's given count (the batcher's, beside other passes)
        self.reach = _reach(self.loaded.vae_meta["mean"], self.loaded.vae_meta["std"])

    def run(self, items: list[Item], *, threads: int | None = None) -> list[Result]:
        """Items without constraints in one pass; each constrained one in a pass of its own, as ``lsgan generate``
        with its constraints and ``--num`` makes them (control optimises a batch together)."""
        from lsgan.constraints import Constraints
        from lsgan.threads import ThreadPolicy

        policy = self.threads
        if threads is not None and self.loaded.device.type == "cpu":
            policy = self._fixed.setdefault(threads, ThreadPolicy(threads=threads))
        plain, constrained = _split(items)
        out: list[Result | None] = [None] * len(items)
        if plain:
            feats, timings = self._features([items[i] for i in plain], policy)
            requests = [items[i].request for i in plain for _ in range(items[i].num)]
            joints = [decoded_motion(r, 0, f).joints for r, f in zip(requests, feats)]
            for i, r in zip(plain, _results([items[i] for i in plain], joints, timings)):
                out[i] = r
        for i in constrained:
            c = Constraints.from_record(items[i].control)
            feats, timings = self._features([items[i]], policy, [c] * items[i].num)
            out[i] = _constrained(items[i], feats, c, timings)
        return out

    def _features(self, items: list[Item], policy, constraints=None) -> tuple[list[np.ndarray], dict]:
        """The pass of :func:`lsgan.generate.run_models` over ``items``: features and timings (s); ``constraints``
        (one per motion) steer the latents, and are met afterwards by :func:`_constrained`."""
        import torch

        from lsgan.generate import noise_dim, run_models

        dim = noise_dim(self.loaded.model, self.loaded.meta)
        noise = torch.from_numpy(np.concatenate([draw_noise(it.seed, it.num, dim) for it in items]))
        feats, timings, _ = run_models(self.loaded, [it.request for it in items], [it.num for it in items], noise,
                                       batch_size=self.batch_size, threads=policy, constraints=constraints,
                                       close=False)
        return feats, timings


class OnnxEngine(Engine):
    """An ``lsgan export-model --onnx`` folder run by onnxruntime (``--model DIR``)."""

    backend = "onnx"

    def __init__(self, folder: str | os.PathLike, *, variant: str = "fp32", threads: int | None = None,
                 batch_size: int = 256, text_cache: int = 1024) -> None:
        from lsgan.deploy.runtime import load

        self.model = load(folder, variant=variant, threads=threads, text_cache=text_cache)
        self.condition = self.model.manifest["condition"]
        self.actions = list(self.model.manifest.get("action_names", [])) if self.condition == "action" else []
        self.max_frames = self.model.max_frames
        self.batch_size = batch_size
        self.reach = _reach(self.model.feature_mean, self.model.feature_std)

    def run(self, items: list[Item], *, threads: int | None = None) -> list[Result]:
        """``threads`` is ignored: onnxruntime fixes a session's threads when it is made (``load_engine``).
        Constrained items are met without being steered first (onnxruntime has no gradients: docs/control.md)."""
        from lsgan.constraints import Constraints

        dim = int(self.model.manifest["noise_dim"])
        plain, constrained = _split(items)
        out: list[Result | None] = [None] * len(items)
        if plain:
            noise = np.concatenate([draw_noise(items[i].seed, items[i].num, dim) for i in plain])
            requests = [items[i].request for i in plain for _ in range(items[i].num)]  # one row of noise each
            result = self.model.generate(requests, noise=noise, batch_size=self.batch_size)
            joints = [m.joints.astype(np.float32) for m in result.motions]
            for i, r in zip(plain, _results([items[i] for i in plain], joints, result.timings_s)):
                out[i] = r
        for i in constrained:
            it = items[i]
            feats, timings = self.model.features([it.request] * it.num, draw_noise(it.seed, it.num, dim),
                                                 self.batch_size)
            out[i] = _constrained(it, feats, Constraints.from_record(it.control), timings)
        return out


def _reach(feat_mean, feat_std) -> dict:
    from lsgan.constraints import model_reach

    speed, skeleton = model_reach(feat_mean, feat_std)
    return {"speed": float(speed), "skeleton": [float(b) for b in skeleton]}


def load_engine(*, gan: str | None = None, vae: str | None = None, model: str | None = None, int8: bool = False,
                device: str = "auto", text_encoder_path: str | None = None, text_cache: int = 1024,
                threads: int | None = None) -> Engine:
    """The torch engine (``gan`` and ``vae``) or the ONNX one (``model``; ``threads`` per session, default the free
    cores), keeping ``text_cache`` prompt embeddings, warmed up by one short pass."""
    t0 = time.perf_counter()
    if model is not None:
        if gan or vae or text_encoder_path:
            raise ValueError("give an exported folder (--model) or checkpoints (--gan and --vae), not both")
        engine: Engine = OnnxEngine(model, variant="int8" if int8 else "fp32", threads=threads,
                                    text_cache=text_cache)
    else:
        if not gan or not vae:
            raise ValueError("give --gan RUN and --vae RUN (or --model EXPORT_DIR)")
        if int8:
            raise ValueError("--int8 goes with --model (an ONNX export made with --int8)")
        engine = TorchEngine(gan, vae, device=device, text_encoder_path=text_encoder_path, text_cache=text_cache)
    warm = Item(text="a person walks forward" if engine.condition == "text" else None,
                action=engine.actions[0] if engine.condition == "action" and engine.actions else None,
                frames=min(40, engine.max_frames))
    engine.run([warm])
    engine.load_s = time.perf_counter() - t0
    return engine
