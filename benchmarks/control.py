"""Control (``generate --path/--keyframe/--continue``, lsgan.control): how closely constraints are met, what it
costs the motion's quality, and how long it takes.

Protocol (OmniControl's, on our data): ``--motions`` windows of ``--split`` (40-120 frames, one per clip,
captioned) are drawn; each caption is generated at its window's length from the same seeds, in the same run:

- ``free``: no constraint (the unconstrained model, the reference for quality and time);
- ``path``: the real window's root path on the ground, every frame (OmniControl's dense pelvis control);
- ``keyframes``: the real window's whole pose (22 joints) at three frames: a third, two thirds, the last;
- ``joints``: some joints of the real window (the head and both wrists) at a third and two thirds: keyframes that
  set some joints, completed by inverse kinematics (lsgan.motion.ik);
- ``path-facing``: the real root path with ``--facing`` (the body turned along the path's direction of travel);
- ``path-unsteered`` and ``keyframes-unsteered``: those constraints met without the optimisation (0 steps),
  which is what the ONNX route does (onnxruntime has no gradients);
- ``continue``: a continuation of the window's first half (``generate --continue``), placed where it ends.

Constraint errors (on the motion of record: the rigid joints every output shows): for the path, OmniControl's
trajectory error (share of motions with a frame more than 50 cm off), location error (share of constrained frames
more than 50 cm off) and average error (mean distance, cm); for keyframes the mean and largest per-joint distance
(cm); for continuations the seam's position, pose and velocity gaps, beside the real windows' own velocity change
there. Quality, per row: R-precision top-3 and FID with ``--evaluator`` (FID against the drawn windows themselves:
MLD's 'same' reference), and lsgan.motion.quality's skating, jerk and penetration. Time: the control part per
motion in batches of 32 and one at a time (``--single`` motions); and whole ``generate`` calls for 120-frame
motions on an S-shaped path, at batch 1 and 32, beside the same calls unconstrained.

    LSGAN_THREADS=2 python benchmarks/control.py --gan runs/bandai-gan --vae runs/bandai-vae --data bandai.h5 \
        --evaluator runs/bandai-evaluator --motions 256 --json control.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np
import torch

from lsgan.constraints import CONTINUE_FRAMES, Constraints, Placement, continuing, frame_at, measure
from lsgan.control import ControlSettings
from lsgan.data.features import recover_from_ric
from lsgan.eval import metrics as M
from lsgan.eval.evaluate import _draw, _windows
from lsgan.generate import Request, draw_noise, load_models, noise_dim, run_models
from lsgan.generation import decoded_motion
from lsgan.models.evaluator import load_evaluator
from lsgan.motion.quality import quality_metrics

FAR = 0.5  # m: OmniControl's threshold for a trajectory or location failure
SOME_JOINTS = (15, 20, 21)  # the ``joints`` row's: head, left wrist, right wrist
UNSTEERED = ControlSettings(noise_steps=0, latent_steps=0)
KINDS = ("free", "path", "path-facing", "keyframes", "joints", "path-unsteered", "keyframes-unsteered")


def constraint_sets(joints: list[np.ndarray]) -> dict[str, list[Constraints]]:
    """Per kind, one constraint set per real window (T, 22, 3)."""
    out: dict[str, list[Constraints]] = {kind: [] for kind in KINDS}
    for j in joints:
        T = len(j)
        some = np.full_like(j, np.nan)
        some[:, SOME_JOINTS] = j[:, SOME_JOINTS]
        out["free"].append(Constraints(T))
        out["path"].append(Constraints(T, path=j[:, 0, [0, 2]]))
        out["keyframes"].append(Constraints(T, keyframes={f: j[f] for f in (T // 3, 2 * T // 3, T - 1)}))
        out["joints"].append(Constraints(T, keyframes={f: some[f] for f in (T // 3, 2 * T // 3)}))
        out["path-facing"].append(Constraints(T, path=j[:, 0, [0, 2]], facing=True))
    out["path-unsteered"], out["keyframes-unsteered"] = out["path"], out["keyframes"]
    return out


def continuation_sets(joints: list[np.ndarray]) -> tuple[list[np.ndarray], list[Constraints], list[Placement]]:
    """Per real window (T, 22, 3): its first half as the motion to continue, and a continuation of T frames."""
    previous = [j[: max(len(j) // 2, 2 * CONTINUE_FRAMES)] for j in joints]
    made = [continuing(p, len(j)) for p, j in zip(previous, joints)]
    return previous, [c for c, _ in made], [p for _, p in made]


def run_kind(loaded, requests, noise, constraints, batch: int, placements=None,
             settings: ControlSettings | None = None) -> tuple[list, float]:
    """Motions of record for the requests (one each) under the constraints, placed; control seconds per motion."""
    feats, timings, _ = run_models(loaded, requests, [1] * len(requests), noise, batch_size=batch,
                                   constraints=None if constraints is None else constraints, control_settings=settings)
    motions = [decoded_motion(r, 0, f) for r, f in zip(requests, feats)]
    for m, p in zip(motions, placements or []):
        m.joints = p.apply(m.joints)
    return motions, timings.get("control", 0.0) / len(requests)


def seam_gaps(previous: list[np.ndarray], motions: list[np.ndarray], k: int = CONTINUE_FRAMES) -> dict:
    """Continuation seams: position gap (cm, mean joint distance over the shared frames), pose gap (cm, the last
    shared frame in its facing frame) and velocity jump (m/s, mean over joints: the first new step against the
    continued motion's last step)."""
    pos, pose, vel = [], [], []
    for p, m in zip(previous, motions):
        pos.append(np.linalg.norm(m[:k] - p[-k:], axis=-1).mean())
        a, b = frame_at(p, len(p) - 1).undo(p[-1]), frame_at(m, k - 1).undo(m[k - 1])
        pose.append(np.linalg.norm(a - b, axis=-1).mean())
        vel.append(np.linalg.norm((m[k] - m[k - 1]) - (p[-1] - p[-2]), axis=-1).mean() * 20)
    return {"seam_position_cm": float(np.mean(pos) * 100), "seam_pose_cm": float(np.mean(pose) * 100),
            "seam_velocity_jump_m_s": float(np.mean(vel))}


def real_velocity_jump(joints: list[np.ndarray]) -> float:
    """The same velocity jump inside the real windows at the seam's frame: how much real motion changes there."""
    out = []
    for j in joints:
        h = max(len(j) // 2, 2 * CONTINUE_FRAMES)
        out.append(np.linalg.norm((j[h] - j[h - 1]) - (j[h - 1] - j[h - 2]), axis=-1).mean() * 20)
    return float(np.mean(out))


def errors(kind: str, motions, constraints) -> dict:
    kind = kind.removesuffix("-unsteered").removesuffix("-facing")
    if kind == "path":
        d = [np.linalg.norm(m.joints[:, 0][:, [0, 2]] - c.path, axis=-1) for m, c in zip(motions, constraints)]
        facing = [measure(m.joints, c).get("facing_deg") for m, c in zip(motions, constraints)]
        facing = [f for f in facing if f]
        return {**({"facing_mean_deg": float(np.mean([f["mean"] for f in facing])),
                    "facing_max_deg": float(max(f["max"] for f in facing))} if facing else {}),"trajectory_error": float(np.mean([x.max() > FAR for x in d])),
                "location_error": float(np.mean(np.concatenate(d) > FAR)),
                "average_error_cm": float(np.mean(np.concatenate(d)) * 100),
                "max_error_cm": float(max(x.max() for x in d) * 100)}
    if kind in ("keyframes", "joints"):
        got = [measure(m.joints, c)["keyframes_m"] for m, c in zip(motions, constraints)]
        return {"keyframe_mean_cm": float(np.mean([g["mean"] for g in got]) * 100),
                "keyframe_max_cm": float(max(g["max"] for g in got) * 100),
                "keyframe_p90_motion_mean_cm": float(np.percentile([g["mean"] for g in got], 90) * 100)}
    return {}


def quality(ev, feats, joints, captions, real_emb, seed: int) -> dict:
    """R-precision top-3, FID against the real windows, skating, jerk, penetration of motions (features, joints)."""
    emb = ev.embed_motions(feats)
    text = ev.embed_texts(captions)
    q = quality_metrics(joints)
    return {"top3": float(M.r_precision(text, emb, rng=seed)[2]), "fid": M.fid(real_emb, emb),
            "skating": q["foot_skating_ratio"], "jerk": q["jerk_m_s3"], "penetration_m": q["penetration_m"]}


def single_times(loaded, requests, noise, constraints, n: int, settings: ControlSettings | None = None) -> float:
    """Seconds of control per motion, one motion at a time."""
    spent = []
    for i in range(min(n, len(requests))):
        _, t = run_kind(loaded, requests[i:i + 1], noise[i:i + 1], constraints[i:i + 1], 1, settings=settings)
        spent.append(t)
    return float(np.median(spent))


def end_to_end(loaded, caption: str, repeats: int) -> dict:
    """Whole ``generate`` calls (text, generator, control, decoder, closing, warping, the motion of record) for
    120-frame motions on an S-shaped path at about 1 m/s: seconds per motion at batch 1 (median of ``repeats``) and
    in one call of 32, and the same unconstrained."""
    from lsgan.constraints import path_points
    from lsgan.generate import generate_loaded

    path = path_points(np.array([[0, 0, 0], [2, 1.0, 1.5], [4, 0.0, 3.5], [5.95, 1.0, 5.5]]), 120)
    c = Constraints(120, path=path)
    req = [Request(text=caption, frames=120)]
    out = {}
    for name, cons in (("free", None), ("path", c)):
        one = []
        for k in range(repeats):
            t0 = time.perf_counter()
            generate_loaded(loaded, req, seed=k, constraints=cons)
            one.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        generate_loaded(loaded, req, num=32, seed=0, constraints=cons)
        out[name] = {"s_per_motion_batch1": float(np.median(one)),
                     "s_per_motion_batch32": (time.perf_counter() - t0) / 32}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gan", required=True)
    ap.add_argument("--vae", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--evaluator", required=True)
    ap.add_argument("--motions", type=int, default=256, help="test windows (a multiple of 32 for R-precision)")
    ap.add_argument("--single", type=int, default=16, help="motions timed one at a time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--split", default="test", help="the windows' split (a small shard's test split may hold fewer "
                    "than --motions)")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"rows to run, of {', '.join(KINDS)} (free is always "
                    "run: the reference)")
    ap.add_argument("--no-continue", action="store_true", help="skip the continuation row and the end-to-end timing")
    ap.add_argument("--json")
    args = ap.parse_args()
    kinds = ["free"] + [k for k in args.kinds.split(",") if k != "free"]
    if set(kinds) - set(KINDS):
        ap.error(f"unknown kinds {sorted(set(kinds) - set(KINDS))}")
    torch.set_num_threads(int(os.environ.get("LSGAN_THREADS", "2")))
    loaded = load_models(args.gan, args.vae, device="cpu")
    ev = load_evaluator(args.evaluator, device="cpu")
    dataset = _windows(args.data, args.split, 40, 120)
    draw = _draw(dataset, args.seed)
    rng = np.random.default_rng(args.seed)
    pick = rng.choice(len(draw.motions), size=min(args.motions, len(draw.motions)) // 32 * 32, replace=False)
    real = [draw.motions[i] for i in pick]
    captions = [draw.captions[i] for i in pick]
    joints = [recover_from_ric(m.astype(np.float32)) for m in real]
    requests = [Request(text=c, frames=len(m)) for c, m in zip(captions, real)]
    noise, _ = draw_noise(args.seed, len(requests), noise_dim(loaded.model, loaded.meta))
    real_emb = ev.embed_motions(real)
    sets = constraint_sets(joints)
    report = {"machine": platform.machine(), "cpus": os.cpu_count(), "threads": torch.get_num_threads(),
              "load_before": os.getloadavg(), "motions": len(requests), "gan": args.gan, "vae": args.vae, "rows": {}}
    for kind in kinds:
        cons, settings = sets[kind], UNSTEERED if kind.endswith("-unsteered") else None
        t0 = time.perf_counter()
        motions, per_motion = run_kind(loaded, requests, noise, None if kind == "free" else cons, 32,
                                       settings=settings)
        row = {**errors(kind, motions, cons),
               **quality(ev, [m.features for m in motions], [m.joints for m in motions], captions, real_emb, args.seed),
               "control_s_per_motion_batch32": per_motion, "wall_s": time.perf_counter() - t0}
        if kind != "free":
            row["control_s_per_motion_batch1"] = single_times(loaded, requests, noise, cons, args.single, settings)
        report["rows"][kind] = row
        print(kind, json.dumps({k: round(v, 4) for k, v in row.items()}), flush=True)
    rq = quality(ev, real, joints, captions, real_emb, args.seed)
    report["rows"]["real"] = rq
    print("real", json.dumps({k: round(v, 4) for k, v in rq.items()}))
    if args.no_continue:
        return _write(report, args.json)
    previous, cons, places = continuation_sets(joints)
    t0 = time.perf_counter()
    motions, per_motion = run_kind(loaded, requests, noise, cons, 32, places)
    row = {**seam_gaps(previous, [m.joints for m in motions]), "real_velocity_jump_m_s": real_velocity_jump(joints),
           **quality(ev, [m.features for m in motions], [m.joints for m in motions], captions, real_emb, args.seed),
           "control_s_per_motion_batch32": per_motion, "wall_s": time.perf_counter() - t0}
    report["rows"]["continue"] = row
    print("continue", json.dumps({k: round(v, 4) for k, v in row.items()}), flush=True)
    report["end_to_end_120_frames"] = end_to_end(loaded, captions[0], args.single)
    print("end to end, 120 frames:", json.dumps(report["end_to_end_120_frames"]), flush=True)
    _write(report, args.json)


def _write(report: dict, path: str | None) -> None:
    report["load_after"] = os.getloadavg()
    if path:
        with open(path, "w") as fh:
            json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
