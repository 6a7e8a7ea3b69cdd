"""Cost of generation (``lsgan bench``): FLOPs per clip and per 2048 clips, and measured time per motion.

FLOPs (2 per multiply-add) are counted by PyTorch's ``FlopCounterMode`` on the real forward passes: matrix
products and attention, not norms or activations. Per model:

- the generator alone (one pass), or the denoiser alone (every sampling step, both halves of classifier-free
  guidance);
- end to end: the text encoder (one pass per clip) + the generator or denoiser + the VAE decoder for ``frames``
  frames. The text encoder counted is the one whose width the model takes. For the paper-sized models that is
  CLIP ViT-L/14's text tower (768-d, built with random weights, captions padded to its 77 tokens as MLD does);
  for checkpoints it is the encoder recorded in them.

Counts are taken on a few clips and scaled. Every operation is per sample, so the counts are exactly linear in
the batch (a test checks this). MLD's released code also runs the text encoder on the empty prompt for guidance.
lsgan's denoiser uses a learned null token instead; ``e2e_gflops_clip_null_text`` gives the figure with that
extra pass.

Time per motion is measured end to end, as a user waits for it: text encoding with an encoder that runs here
(MiniLM; its embedding is zero-padded to a wider model's condition), then the generator or denoiser, then VAE
decoding. It is taken at batch 1 and 256, per stage and in total, as the median of ``repeats`` runs after a
warm-up. Models are paper-sized (``recipes/humanml3d.yaml``) with random weights unless checkpoints are given.
:func:`time_per_motion` is the one timer of generation: ``benchmarks/models.py`` times every runtime with it.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode, sdpa_flop_count

from lsgan.models.gan import GANConfig, LatentGAN
from lsgan.models.text import CLIP_L14_TEXT, TextEncoder, clip_l14_text_tower
from lsgan.models.vae import MotionVAE, VAEConfig
from lsgan.threads import LARGE_BATCH, ThreadPolicy, threads_said

CLIPS = 2048  # the paper's unit
FLOP_BATCH = 32  # clips counted for a generator or denoiser
PART_FLOP_BATCH = 2  # clips counted for a text encoder or a VAE decoder
BATCHES = (1, 256)  # timed batch sizes
CLIP_TOKENS = CLIP_L14_TEXT["max_position_embeddings"]  # MLD pads every caption to CLIP's 77 tokens
PAPER_TEXT_ENCODER = "clip-vit-l-14"
PAPER_COND_DIM = CLIP_L14_TEXT["projection_dim"]  # 768: the paper's condition
# recipes/humanml3d.yaml (MLD's VAE: post-norm, 256 positions; a test compares them)
PAPER_VAE = VAEConfig(latent_dim=256, d_model=256, num_layers=9, num_heads=4, ff_size=1024, dropout=0.1,
                      activation="gelu", position_embedding="learned", max_len=256, norm_first=False)
PAPER_GAN = dict(noise_dim=100, latent_dim=256, cond="text", cond_dim=PAPER_COND_DIM, hidden_dim=512,
                 num_res_blocks=2, leaky_slope=0.2)
PAPER_GANS = ("deep-wgan-gp", "vanilla-wgan-gp")
# MLD's denoiser (configs/modules/denoiser.yaml): 9 layers, width 256, 4 heads, ff 1024, one 256-d latent token.
PAPER_DIFFUSION = dict(latent_dim=256, d_model=256, num_layers=9, num_heads=4, ff_size=1024, dropout=0.1,
                       norm_first=False, cond="text", cond_dim=PAPER_COND_DIM)


@dataclass
class BenchRow:
    """One line of the table; the JSON keys are the field names. FLOPs in G (1e9), per clip unless ``_2048``."""

    model: str
    gflops_2048: float  # the generator or denoiser alone, 2048 clips
    ms_per_motion_b1: float  # measured, end to end
    ms_per_motion_b256: float
    device: str
    kind: str  # "gan" or "diffusion"
    cond_dim: int
    text_encoder_counted: str
    text_gflops_clip: float
    generator_gflops_clip: float  # the generator or denoiser alone
    decoder_gflops_clip: float
    e2e_gflops_clip: float  # text + generator/denoiser + decoder
    e2e_gflops_2048: float
    e2e_gflops_clip_null_text: float  # plus a text pass on the empty prompt where guidance needs one (MLD's code)
    frames: int
    text_encoder_timed: str
    ms_text_b1: float
    ms_generator_b1: float
    ms_decoder_b1: float
    ms_text_b256: float
    ms_generator_b256: float
    ms_decoder_b256: float
    threads: str  # "adaptive (up to N)" or "N (fixed)": lsgan's thread policy during the timing
    load_avg: float | None  # 1-minute load average when the row's timing began
    ms_per_motion_b1_q25: float = 0.0  # quartiles of the total over the runs: the spread of the median
    ms_per_motion_b1_q75: float = 0.0
    ms_per_motion_b256_q25: float = 0.0
    ms_per_motion_b256_q75: float = 0.0


@dataclass
class Sampler:
    """A latent generator as the benchmark sees it: ``sample(cond) -> latents (B, Z)`` for embeddings (B, D)."""

    name: str
    sample: Callable[[torch.Tensor], torch.Tensor]
    cond_dim: int
    to: Callable[[torch.device], None]
    kind: str = "gan"
    text_encoder: str = PAPER_TEXT_ENCODER  # the encoder whose embeddings it takes (counted end to end)
    null_text: bool = False  # guided: MLD's code encodes the empty prompt too


def _cpu_sdpa_flops(query_shape, key_shape, value_shape, *args, out_shape=None, **kwargs) -> int:
    """Attention on the CPU: torch's counter registers the GPU kernels only."""
    return sdpa_flop_count(query_shape, key_shape, value_shape)


def count_flops(fn: Callable[[], object]) -> int:
    """Floating-point operations of one call of ``fn`` (PyTorch's count: a multiply-add is 2).

    Transformer layers in eval mode take a fused fast path that the counter does not see, so it is switched off
    while counting (the arithmetic is the same)."""
    fastpath = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)
    extra = {torch.ops.aten._scaled_dot_product_flash_attention_for_cpu: _cpu_sdpa_flops}
    try:
        with FlopCounterMode(display=False, custom_mapping=extra) as counter, torch.no_grad():
            fn()
    finally:
        torch.backends.mha.set_fastpath_enabled(fastpath)
    return int(counter.get_total_flops())


def paper_gan(arch: str, cond_dim: int = PAPER_COND_DIM) -> GANConfig:
    """The paper's GAN ``arch`` for conditions of ``cond_dim`` (MiniLM's 384, CLIP's 768)."""
    return GANConfig(arch=arch, **{**PAPER_GAN, "cond_dim": cond_dim})


def save_paper_runs(folder: Path, arch: str = "deep-wgan-gp") -> tuple[Path, Path]:
    """The paper-sized VAE and a GAN on MiniLM's 384-d embeddings, random weights, saved as lsgan runs in ``folder``
    (features and latents left unnormalised: mean 0, std 1): what the benchmarks export and time. -> (gan, vae)."""
    from lsgan.models.checkpoint import save_checkpoint, weights_hash
    from lsgan.models.text import load_text_encoder

    torch.manual_seed(0)
    vae_run, gan_run = folder / "vae", folder / "gan"
    save_checkpoint(vae_run / "best", model=MotionVAE(PAPER_VAE), kind="vae", config={"model": asdict(PAPER_VAE)},
                    step=0, extra={"mean": [0.0] * 263, "std": [1.0] * 263})
    config = paper_gan(arch, cond_dim=384)
    z = config.latent_dim
    save_checkpoint(gan_run / "best", model=LatentGAN(config), kind="gan", config={"gan": asdict(config)},
                    step=0, extra={"latent_mean": [0.0] * z, "latent_std": [1.0] * z, "vae_hash": weights_hash(vae_run),
                                   "text_encoder": load_text_encoder("minilm").id})
    return gan_run, vae_run


def gan_sampler(arch: str, gan: LatentGAN | None = None, cond_dim: int = PAPER_COND_DIM,
                text_encoder: str = PAPER_TEXT_ENCODER) -> Sampler:
    """The generator of a GAN (paper-sized, random weights, when ``gan`` is None)."""
    model = gan if gan is not None else LatentGAN(paper_gan(arch, cond_dim))
    model.eval()
    noise_dim = model.config.noise_dim

    def sample(cond: torch.Tensor) -> torch.Tensor:
        return model.generator(torch.randn(cond.shape[0], noise_dim, device=cond.device), cond)

    return Sampler(arch, sample, model.config.cond_dim, lambda d: model.to(d), "gan", text_encoder)


def diffusion_sampler(model=None, *, steps: int, guidance: float, name: str = "mld-diffusion",
                      text_encoder: str = PAPER_TEXT_ENCODER) -> Sampler:
    """A latent-diffusion model (paper-sized, random weights, when None) sampled with DDIM over ``steps`` steps
    and classifier-free ``guidance`` (two denoiser passes per step unless guidance is 1)."""
    from lsgan.models.diffusion import DiffusionConfig, LatentDiffusion

    model = (model if model is not None else LatentDiffusion(DiffusionConfig(**PAPER_DIFFUSION))).eval()

    def sample(cond: torch.Tensor) -> torch.Tensor:
        g = torch.Generator(device="cpu").manual_seed(0)
        return model.sample(cond, generator=g, steps=steps, guidance=guidance)

    return Sampler(f"{name} ({steps} DDIM steps, cfg {guidance:g})", sample, model.config.cond_dim,
                   lambda d: model.to(d), "diffusion", text_encoder, guidance != 1.0)


def _checkpoint_sampler(path, steps: int, guidance: float) -> Sampler:
    from lsgan.generate import load_generator

    model, meta = load_generator(path)
    if model.config.cond != "text":
        raise ValueError(f"{path}: bench times text-conditioned generators; this one is {model.config.cond}")
    encoder = str((meta.get("extra") or {}).get("text_encoder", "minilm")).split(":")[0]
    if hasattr(model, "generator"):
        return gan_sampler(model.config.arch, model, text_encoder=encoder)
    return diffusion_sampler(model, steps=steps, guidance=guidance, name=Path(str(path)).name, text_encoder=encoder)


def bench_samplers(*, gans=(), diffusion=None, vae=None, steps: int = 50, guidance: float = 7.5,
                   ) -> tuple[list[Sampler], MotionVAE | None]:
    """The samplers ``lsgan bench`` measures: the given checkpoints, or paper-sized GANs and MLD denoiser."""
    samplers = [_checkpoint_sampler(path, steps, guidance) for path in gans]
    if not gans:
        samplers = [gan_sampler(arch) for arch in PAPER_GANS]
    if diffusion is not None:
        samplers.append(_checkpoint_sampler(diffusion, steps, guidance))
    elif not gans:
        samplers.append(diffusion_sampler(steps=steps, guidance=guidance))
    decoder = None
    if vae is not None:
        from lsgan.models.vae import load_vae

        decoder, _ = load_vae(vae)
    return samplers, decoder


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench_prompts(batch: int) -> list[str]:
    return [f"a person walks forward and waves the {'left' if i % 2 else 'right'} hand {i} times"
            for i in range(batch)]


def generator_flops(sampler: Sampler, device: torch.device | str = "cpu") -> float:
    """FLOPs per clip of the generator, or of the denoiser over all its steps (counted on FLOP_BATCH clips)."""
    cond = torch.nn.functional.normalize(torch.randn(FLOP_BATCH, sampler.cond_dim, device=device), dim=-1)
    return count_flops(lambda: sampler.sample(cond)) / FLOP_BATCH


def gflops_2048(sampler: Sampler, device: torch.device) -> float:
    """GFLOPs of sampling 2048 latents (counted on FLOP_BATCH clips, scaled exactly)."""
    return generator_flops(sampler, device) * CLIPS / 1e9


def decoder_flops(vae: MotionVAE, frames: int, clips: int = PART_FLOP_BATCH) -> float:
    """FLOPs per clip of decoding one latent into ``frames`` frames (on the CPU)."""
    vae.to("cpu")
    z = torch.randn(clips, vae.config.latent_dim)
    mask = torch.ones(clips, frames, dtype=torch.bool)
    return count_flops(lambda: vae.decode(z, mask)) / clips


def clip_text_flops(tokens: int = CLIP_TOKENS, clips: int = PART_FLOP_BATCH) -> float:
    """FLOPs per clip of CLIP ViT-L/14's text tower + projection on ``tokens`` tokens (random weights)."""
    model = clip_l14_text_tower()
    ids = torch.randint(0, CLIP_L14_TEXT["vocab_size"] - 2, (clips, tokens))  # ids, not the special tokens
    return count_flops(lambda: model(input_ids=ids)) / clips


def text_cost(name: str, cond_dim: int) -> tuple[str, float]:
    """(what was counted, FLOPs per clip) of one pass of the text encoder ``name`` giving ``cond_dim`` wide
    embeddings: CLIP ViT-L/14 on CLIP_TOKENS tokens, or MiniLM on the timed prompts."""
    from lsgan.models.text import load_text_encoder

    if name == PAPER_TEXT_ENCODER and cond_dim == PAPER_COND_DIM:
        return f"clip-vit-l-14 text tower, {CLIP_TOKENS} tokens ({cond_dim}-d)", clip_text_flops()
    if name == "minilm":
        enc = load_text_encoder("minilm")
        if enc.dim == cond_dim:
            prompts = bench_prompts(PART_FLOP_BATCH)
            flops = count_flops(lambda: enc.encode(prompts)) / len(prompts)
            return f"minilm, the timed prompts ({cond_dim}-d)", flops
    raise ValueError(f"bench cannot count the text encoder {name!r} for a {cond_dim}-wide condition "
                     f"(it counts clip-vit-l-14 at {PAPER_COND_DIM} and minilm)")


def count_costs(samplers: list[Sampler], decoder: MotionVAE, frames: int,
                progress: Callable[[str], None] | None = None) -> list[dict[str, float | str]]:
    """Per sampler, FLOPs per clip of its text encoder, its generator or denoiser, and the decoder (on the CPU)."""
    texts: dict[tuple[str, int], tuple[str, float]] = {}
    dec = decoder_flops(decoder, frames)
    out = []
    for s in samplers:
        if progress:
            progress(f"[count] {s.name}")
        key = (s.text_encoder, s.cond_dim)
        if key not in texts:
            texts[key] = text_cost(*key)
        s.to(torch.device("cpu"))
        out.append(dict(text_name=texts[key][0], text=texts[key][1], generator=generator_flops(s), decoder=dec))
    return out


def _fit(emb: torch.Tensor, dim: int) -> torch.Tensor:
    """The timed encoder's embeddings at the model's condition width (zero-padded or cut)."""
    if emb.shape[1] < dim:
        return torch.nn.functional.pad(emb, (0, dim - emb.shape[1]))
    return emb[:, :dim]


@dataclass
class Pipeline:
    """What is timed end to end, in three stages: ``encode(prompts) -> conditions``, ``sample(conditions) ->
    latents``, ``decode(latents, frames) -> features``; ``sync`` waits for the device. Any runtime fits (torch eager,
    onnxruntime, ...), so one timer serves ``lsgan bench`` and ``benchmarks/models.py``."""

    encode: Callable[[list[str]], object]
    sample: Callable[[object], object]
    decode: Callable[[object, int], object]
    sync: Callable[[], None] = lambda: None


def torch_pipeline(sampler: Sampler, vae: MotionVAE, encode: Callable[[list[str]], torch.Tensor],
                   device: torch.device) -> Pipeline:
    """lsgan's torch path: the timed encoder's embeddings fitted to the sampler's width, its latents, the VAE."""

    def decode(z: torch.Tensor, frames: int) -> torch.Tensor:
        return vae.decode(z, torch.ones(z.shape[0], frames, dtype=torch.bool, device=device))

    return Pipeline(lambda prompts: _fit(encode(prompts).to(device), sampler.cond_dim), sampler.sample, decode,
                    lambda: _sync(device))


def time_per_motion(pipeline: Pipeline, *, batch: int, frames: int, repeats: int) -> dict[str, float]:
    """Wall time per motion (ms) at ``batch`` over ``repeats`` runs after a warm-up: the median of ``total`` and of
    the stages ``text``, ``generator``, ``decoder``, and the quartiles ``total_q25`` / ``total_q75``. Threads follow
    lsgan's policy (:class:`lsgan.threads.ThreadPolicy`), as in ``lsgan generate``."""
    prompts = bench_prompts(batch)
    laps: dict[str, list[float]] = {"text": [], "generator": [], "decoder": [], "total": []}
    with torch.no_grad(), ThreadPolicy(large=batch >= LARGE_BATCH) as threads:
        for r in range(repeats + 1):
            threads.update()
            pipeline.sync()
            t = [time.perf_counter()]
            cond = pipeline.encode(prompts)
            pipeline.sync()
            t.append(time.perf_counter())
            z = pipeline.sample(cond)
            pipeline.sync()
            t.append(time.perf_counter())
            pipeline.decode(z, frames)
            pipeline.sync()
            t.append(time.perf_counter())
            if r or not repeats:  # round 0 warms up
                for i, stage in enumerate(("text", "generator", "decoder")):
                    laps[stage].append(1000.0 * (t[i + 1] - t[i]) / batch)
                laps["total"].append(1000.0 * (t[3] - t[0]) / batch)
    out = {k: float(np.median(v)) for k, v in laps.items()}
    out["total_q25"], out["total_q75"] = (float(q) for q in np.percentile(laps["total"], [25, 75]))
    return out


def peak_gflops(precision: str, n: int = 2048, reps: int = 5) -> float:
    """This CPU's matrix-product rate (GFLOP/s; int8: GOP/s) at ``precision``, best of ``reps`` n-cube products on
    every usable core: the roof the floor is computed from."""
    if precision == "int8":
        a, b = (torch.randint(-128, 128, (n, n), dtype=torch.int8) for _ in range(2))
        product = lambda: torch._int_mm(a, b)  # noqa: E731
    else:
        dtype = torch.bfloat16 if precision == "bf16" else torch.float32
        a, b = (torch.randn(n, n, dtype=dtype) for _ in range(2))
        product = lambda: a @ b  # noqa: E731
    with ThreadPolicy(large=True):
        product()
        best = min(_seconds(product) for _ in range(reps))
    return 2 * n**3 / best / 1e9


def _seconds(fn: Callable) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def machine_rate() -> float:
    """This machine's int8 rate right now (GOP/s: a 1024-cube product on every usable core, best of 3, ~10 ms), for
    benchmarks to take before and after each measurement. On a shared host it drops for seconds at a time with no
    other process running and no steal time counted (the int8 decoder at batch 1 then takes up to 1.8x as long),
    so a figure taken in such a stretch can say so."""
    return peak_gflops("int8", n=1024, reps=3)


def _timed_name(enc: TextEncoder, cond_dim: int) -> str:
    fit = "" if enc.dim == cond_dim else f", {'zero-padded' if enc.dim < cond_dim else 'cut'} to {cond_dim}"
    return f"{enc.id.split(':')[0]} ({enc.dim}-d{fit})"


def _load_avg() -> float | None:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def _row(sampler: Sampler, cost: dict, times: dict[int, dict[str, float]], device: torch.device, frames: int,
         timed: str, load_avg: float | None) -> BenchRow:
    text, gen, dec = (cost[k] / 1e9 for k in ("text", "generator", "decoder"))
    e2e = text + gen + dec
    b1, b256 = times[1], times[256]
    return BenchRow(
        sampler.name, gen * CLIPS, b1["total"], b256["total"], str(device), sampler.kind, sampler.cond_dim,
        cost["text_name"], text, gen, dec, e2e, e2e * CLIPS, e2e + (text if sampler.null_text else 0.0), frames,
        timed, b1["text"], b1["generator"], b1["decoder"], b256["text"], b256["generator"], b256["decoder"],
        threads_said(), load_avg, b1["total_q25"], b1["total_q75"], b256["total_q25"], b256["total_q75"])


def run_bench(samplers: list[Sampler], *, vae: MotionVAE | None = None, devices: list[str] | None = None,
              frames: int = 120, repeats: int = 3, text_encoder: str = "minilm",
              progress: Callable[[str], None] | None = None) -> list[BenchRow]:
    """One row per sampler and device: FLOPs per clip and per 2048 clips (the generator or denoiser alone and end
    to end), and ms per motion at batch 1 and 256 with the text encoder ``text_encoder``."""
    from lsgan.models.text import load_text_encoder

    devices = devices or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    torch.manual_seed(0)
    decoder = (vae if vae is not None else MotionVAE(PAPER_VAE)).eval()
    costs = count_costs(samplers, decoder, frames, progress)
    rows = []
    for dev_name in devices:
        device = torch.device(dev_name)
        enc: TextEncoder = load_text_encoder(text_encoder, device=device)
        decoder.to(device)
        for sampler, cost in zip(samplers, costs):
            sampler.to(device)
            if progress:
                progress(f"[{device}] {sampler.name}")
            load_avg = _load_avg()
            pipeline = torch_pipeline(sampler, decoder, enc.encode, device)
            times = {b: time_per_motion(pipeline, batch=b, frames=frames, repeats=repeats) for b in BATCHES}
            rows.append(_row(sampler, cost, times, device, frames, _timed_name(enc, sampler.cond_dim), load_avg))
    return rows


def _num(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.2f}" if x >= 1 else f"{x:.2g}"


def _ms(r: BenchRow, b: int) -> str:
    total, text, gen, dec = (getattr(r, k) for k in (f"ms_per_motion_b{b}", f"ms_text_b{b}",
                                                      f"ms_generator_b{b}", f"ms_decoder_b{b}"))
    return f"{_num(total)} ({_num(text)} + {_num(gen)} + {_num(dec)})"


def format_table(rows: list[BenchRow]) -> str:
    """Markdown: a legend saying what each column counts, the table, and each diffusion row against the first."""
    if not rows:
        return "(no rows)"
    r0 = rows[0]
    loads = [r.load_avg for r in rows if r.load_avg is not None]
    load = f"{min(loads):.2f}-{max(loads):.2f}" if loads else "n/a"
    lines = [
        "FLOPs = 2 x multiply-adds (torch FlopCounterMode: matmuls and attention; norms and activations not "
        "counted), in G (1e9), PER CLIP unless the column says 2048 clips (= 2048 x per clip). "
        "text: one pass of the encoder named (random weights where no checkpoint gives it); generator / denoiser: "
        "one generator pass, or every DDIM step with both guidance halves; VAE decoder: "
        f"{r0.frames} frames; end to end = text + generator / denoiser + VAE decoder.",
        f"ms/motion: measured wall time per motion, total (text + generator / denoiser + decoder), text encoded "
        f"with {', '.join(dict.fromkeys(r.text_encoder_timed for r in rows))}, median of runs after a warm-up; "
        f"quartiles of the runs in the JSON; torch threads: {r0.threads}; "
        f"1-minute load average at the start of the rows: {load}.",
        "",
        "| model | device | text encoder counted | text | generator / denoiser | VAE decoder | end to end | "
        "generator / denoiser, 2048 clips | end to end, 2048 clips | generator vs first | end to end vs first | "
        "ms/motion b1 (text + gen + dec) | ms/motion b256 (text + gen + dec) |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        base = next(b for b in rows if b.device == r.device)
        lines.append(
            f"| {r.model} | {r.device} | {r.text_encoder_counted} | {r.text_gflops_clip:.3f} | "
            f"{r.generator_gflops_clip:.5g} | {r.decoder_gflops_clip:.3f} | {r.e2e_gflops_clip:.3f} | "
            f"{r.gflops_2048:,.2f} | {r.e2e_gflops_2048:,.0f} | x{r.gflops_2048 / base.gflops_2048:,.1f} | "
            f"x{r.e2e_gflops_clip / base.e2e_gflops_clip:.2f} | {_ms(r, 1)} | {_ms(r, 256)} |")
    return "\n".join(lines + [""] + summary_lines(rows))


def summary_lines(rows: list[BenchRow]) -> list[str]:
    """The first row against every diffusion row (FLOPs, the same on every device): how much cheaper, the
    generator alone and end to end."""
    out, base = [], rows[0]
    for r in rows:
        if r.device != base.device or r.kind != "diffusion" or base.kind == "diffusion":
            continue
        line = (f"{base.model} vs {r.model}: the generator is x{r.gflops_2048 / base.gflops_2048:,.0f} cheaper; "
                f"a whole motion is {100 * (1 - base.e2e_gflops_clip / r.e2e_gflops_clip):.0f}% cheaper "
                f"({base.e2e_gflops_clip:.2f} vs {r.e2e_gflops_clip:.2f} GFLOPs per clip)")
        if r.e2e_gflops_clip_null_text != r.e2e_gflops_clip:
            line += (f"; {100 * (1 - base.e2e_gflops_clip / r.e2e_gflops_clip_null_text):.0f}% against MLD's "
                     f"released code, which also encodes the empty prompt ({r.e2e_gflops_clip_null_text:.2f})")
        out.append(line + ".")
    return out


def rows_as_dicts(rows: list[BenchRow]) -> list[dict]:
    return [asdict(r) for r in rows]
