"""What a generation is and how it is written: requests, motions, and the output folder of ``lsgan generate``.

Torch-free, so that both runtimes share it: the torch one (:mod:`lsgan.generate`) and the ONNX one
(:mod:`lsgan.deploy.runtime`), which must run where torch is not installed.
"""
from __future__ import annotations

import json
import os
import re
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsgan import outputs
from lsgan.data.features import recover_from_ric
from lsgan.data.skeleton import FPS
from lsgan.motion.rigid import make_rigid
from lsgan.io import atomic_file


MIN_FRAMES = 4  # the shortest motion lsgan makes (the decoder's time filter and the feet need a few frames)
CPU_DECODE_FRAMES = 4096  # padded frames per decoder pass on a CPU


def decode_batches(frames: list[int], batch_size: int, frame_budget: int | None = None) -> list[list[int]]:
    """Indices of the motions of each decoder pass: sorted by length (little padding), at most ``batch_size``
    motions and, when ``frame_budget`` is given, at most that many padded frames (one motion at least).

    The budget keeps a CPU pass's activations in cache: the paper-sized decoder took 17.9 ms per motion at 256
    motions of 120 frames against 15.4 at 32, and 45 against 25 ms at 196 frames, where the attention scores of
    256 motions alone are 157 MB.
    """
    order = sorted(range(len(frames)), key=lambda i: frames[i])
    batches: list[list[int]] = []
    for i in order:
        longest = frames[i]  # sorted: the newest is the longest of its batch
        if batches and len(batches[-1]) < batch_size \
                and (frame_budget is None or (len(batches[-1]) + 1) * longest <= frame_budget):
            batches[-1].append(i)
        else:
            batches.append([i])
    return batches


@dataclass
class Request:
    """One condition to generate for: a prompt or an action label, and a length in frames (20 fps)."""

    text: str | None = None
    action: str | None = None
    frames: int = 120


@dataclass
class Motion:
    request: Request
    sample: int
    features: np.ndarray  # (T, 263), de-normalised
    joints: np.ndarray  # (T, 22, 3): the motion of record, made rigid (lsgan.motion.rigid)
    raw_joints: np.ndarray | None = None  # (T, 22, 3): recover_from_ric of the features, as decoded
    control: dict | None = None  # constraints given: how far ``joints`` are from them (lsgan.constraints.measure)


def draw_noise(seed: int, n: int, dim: int) -> np.ndarray:
    """The starting noise (n, dim) float32 ~ N(0, 1) of ``seed`` in every runtime (torch, ONNX, the server): numpy's
    ``default_rng(seed).standard_normal``, so that one seed gives one motion whichever runtime runs the model."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    return np.random.default_rng(seed).standard_normal((n, dim), dtype=np.float32)


def decoded_motion(request: Request, sample: int, features: np.ndarray, fix_feet: bool = False) -> Motion:
    """The Motion of decoded features (T, 263): joints recovered once and made rigid once, the raw ones kept.
    ``fix_feet``: the feet held still while the features' contact channels say so (:mod:`lsgan.motion.feet`),
    once, on this motion of record, so that every output shows the same feet."""
    features = np.asarray(features, dtype=np.float32)
    raw = recover_from_ric(features)
    joints = make_rigid(raw)
    if fix_feet:
        from lsgan.motion.feet import contacts_from_features, fix_feet as hold_feet

        joints = hold_feet(joints, contacts_from_features(features)).astype(np.float32)
    return Motion(request=request, sample=sample, features=features, joints=joints, raw_joints=raw)


def place_measured(motions: list[Motion], each: list, placement=None) -> None:
    """Record on each motion how far it is from its constraints (:func:`lsgan.constraints.measure`, in its own
    frame), then move it where ``placement`` (a :class:`lsgan.constraints.Placement`) puts it. Every runtime's last
    step of control."""
    from lsgan.constraints import measure

    for m, c in zip(motions, each, strict=True):
        m.control = measure(m.joints, c)
        if placement is not None:
            m.joints, m.raw_joints = placement.apply(m.joints), placement.apply(m.raw_joints)


@dataclass
class Generation:
    motions: list[Motion]
    timings_s: dict[str, float] = field(default_factory=dict)
    gan: str = ""  # the generator checkpoint (GAN or diffusion; the name is kept for compatibility)
    vae: str = ""
    seed: int = 0
    kind: str = "gan"  # "gan" or "diffusion"
    sampling: dict = field(default_factory=dict)  # diffusion: {"steps", "guidance", "eta"}; GAN: {}
    runtime: dict = field(default_factory=lambda: {"name": "torch"})  # onnx: {"name", "dir", "variant", "threads"}
    # {"generator": {"path", "sha256"}, "vae": {...}} when known without reading the checkpoints (an ONNX export
    # records them); None: hashed from ``gan`` and ``vae`` when written
    checkpoints: dict | None = None
    timeline: dict | None = None  # ``generate --timeline``: its segments and how they were joined (lsgan.timeline)
    fix_feet: bool = False  # the motions' feet held still in contact (decoded_motion), once, for every output
    control: dict | None = None  # constraints given: what they were and the optimiser's settings (lsgan.control)

    @property
    def ms_per_motion(self) -> float:
        return 1000.0 * sum(self.timings_s.values()) / max(len(self.motions), 1)

    @property
    def inputs(self) -> list[str]:
        """What was read to make these motions (an output may not lie inside it): the ONNX folder or the checkpoints."""
        return [self.runtime["dir"]] if "dir" in self.runtime else [self.gan, self.vae]


PROMPT_CONTROLS = "\t\n\r"  # whitespace a pasted prompt may hold; the tokenizer reads it as spaces


def text_problem(text: str) -> str | None:
    """What makes ``text`` no prompt, in words, or None: empty, or holding a control character, a line or paragraph
    separator, or a lone surrogate. The one check of a prompt's text, wherever it comes from (``--text``, a prompts
    file, the library, the server)."""
    bad = next((c for c in text if (unicodedata.category(c) in ("Cc", "Zl", "Zp") and c not in PROMPT_CONTROLS)
                or unicodedata.category(c) == "Cs"), None)
    if bad is not None:
        kind = "a lone surrogate" if unicodedata.category(bad) == "Cs" else "a control character"
        return f"text holds {kind} (U+{ord(bad):04X}); give printable text"
    if not text.strip():
        return 'text is empty: describe a motion, e.g. "a person walks forward"'
    return None


def check_prompts(requests: list[Request]) -> None:
    """Refuse (ValueError) a request whose text is no prompt (:func:`text_problem`), naming it by its number: what
    every generator runs first, torch's and the ONNX runtime's alike."""
    for i, r in enumerate(requests, 1):
        if r.text is not None and (problem := text_problem(r.text)):
            raise ValueError(f"request {i} ({short_text(r.text)!r}): {problem}")


def short_text(text: str, limit: int = 40) -> str:
    """``text`` cut to ``limit`` characters, '...' marking a cut."""
    return text[:limit] + ("..." if len(text) > limit else "")


def read_prompts(path: str | os.PathLike, default_frames: int) -> list[Request]:
    """One prompt per line, optionally ``prompt#frames``; blank lines and lines starting with '//' are skipped. What
    follows a line's last '#' must be a whole number of frames (a typo there is an error, not part of the prompt);
    a prompt that holds a '#' itself ends with its frames (``track #5 dance#120``). A byte-order mark is dropped."""
    from lsgan.errors import reading

    out = []
    with reading(path, "a prompts file of UTF-8 text"):
        text = Path(path).read_text(encoding="utf-8-sig")
    for number, line in enumerate(text.split("\n"), 1):  # lines as an editor counts them, not str.splitlines's
        line = line.strip()
        if not line or line.startswith("//"):
            continue
        m = re.fullmatch(r"(.*)#\s*([0-9]+)\s*", line)
        if "#" in line and not m:
            tail = line.rpartition("#")[2].strip()
            raise ValueError(f"{path}: line {number}: {short_text(tail)!r} after '#' is "
                             "not a number of frames (write prompt#frames, e.g. 'a person walks#120'; a prompt that "
                             "holds a '#' ends with its frames)")
        if m and not MIN_FRAMES <= int(m.group(2)) <= 100_000:
            raise ValueError(f"{path}: line {number} asks for {int(m.group(2))} frames: a motion has {MIN_FRAMES} "
                             "to 100,000")
        request = Request(text=m.group(1).strip(), frames=int(m.group(2))) if m else Request(text=line,
                                                                                             frames=default_frames)
        if problem := text_problem(request.text):
            raise ValueError(f"{path}: line {number}: {problem}")
        out.append(request)
    return out


def _slug(text: str, limit: int = 40) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:limit] or "motion"


def _checkpoints(result: Generation) -> dict:
    """The generator and VAE checkpoints by path and weights hash (reads them: needs torch)."""
    if result.checkpoints is not None:
        return result.checkpoints
    from lsgan.models.checkpoint import resolve, weights_hash

    return {name: {"path": str(resolve(path)), "sha256": weights_hash(path)}
            for name, path in (("generator", result.gan), ("vae", result.vae))}


def write_generation(result: Generation, out: str | os.PathLike, *, force: bool = False,
                     raw_joints: bool = False) -> Path:
    """features ``.npy``, joints ``.npy`` (T,22,3, rigid) per motion and ``manifest.json``; returns the manifest
    path. ``raw_joints`` also writes each motion's decoded joints before they were made rigid (``_joints_raw.npy``,
    a name ``lsgan export`` passes over).

    An existing ``out`` is refused unless ``force``, which first clears the files an earlier lsgan run wrote
    there (and only those).
    """
    stems = motion_stems([m.request for m in result.motions])
    out = claim_generation(out, *result.inputs, force=force, files=generation_files(stems, raw_joints))
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, (m, stem) in enumerate(zip(result.motions, stems)):
        arrays = [("features", m.features), ("joints", m.joints)]
        if raw_joints:
            arrays.append(("joints_raw", m.raw_joints if m.raw_joints is not None else recover_from_ric(m.features)))
        for suffix, array in arrays:
            with atomic_file(outputs.claim_file(out / f"{stem}_{suffix}.npy", force=True)) as fh:
                np.save(fh, array)
        entries.append({
            "index": i, "text": m.request.text, "action": m.request.action, "frames": int(len(m.features)),
            "seconds": len(m.features) / FPS, "sample": m.sample, "features": f"{stem}_features.npy",
            "joints": f"{stem}_joints.npy", **({"raw_joints": f"{stem}_joints_raw.npy"} if raw_joints else {}),
            **({"control": m.control} if m.control is not None else {}),
        })
    sources = _checkpoints(result)
    generator = sources["generator"]
    manifest = {
        "seed": result.seed,
        "fix_feet": result.fix_feet,
        "fps": FPS,
        "generator": {"kind": result.kind, **generator, **result.sampling},
        "gan": generator,  # the generator checkpoint under its historical key, whatever its kind
        "vae": sources["vae"],
        "runtime": result.runtime,
        "timings_s": result.timings_s,
        "ms_per_motion": result.ms_per_motion,
        "motions": entries,
    }
    if result.timeline is not None:
        manifest["timeline"] = result.timeline
    if result.control is not None:
        manifest["control"] = result.control
    path = outputs.claim_file(out / "manifest.json", force=True)
    with atomic_file(path, "w", encoding="utf-8") as fh:
        json.dump(manifest, fh, indent=1)
    return path


def motion_stems(requests: list[Request]) -> list[str]:
    """The file stem of each motion (one request per motion, in order): ``000_a-person-walks``."""
    return [f"{i:03d}_{_slug(r.text or r.action or 'motion')}" for i, r in enumerate(requests)]


def generation_files(stems: list[str], raw_joints: bool = False) -> list[str]:
    """The names :func:`write_generation` writes for motions of these stems."""
    suffixes = ("features", "joints") + (("joints_raw",) if raw_joints else ())
    return [f"{stem}_{x}.npy" for stem in stems for x in suffixes] + ["manifest.json"]


def claim_generation(out: str | os.PathLike, *inputs: str | os.PathLike, force: bool = False,
                     files: list[str] = ()) -> Path:
    """Check (before generating) that ``out`` may be written: see :func:`write_generation`. ``files``: the names
    the run will write, each refused first if it may not be replaced (before an earlier run's files are cleared)."""
    outputs.check_replaceable([Path(out) / name for name in files], force=force)
    return outputs.claim_folder(out, force=force, inputs=inputs)
