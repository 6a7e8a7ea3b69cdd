"""Fit an SMPL-family body to (T,22,3) joint positions: the parameters behind ``lsgan export --body-model``.

HumanML3D's frame is the body models' own (Y up, the body facing +Z, left = +X, metres), so the fitted
``global_orient`` needs no axis change. Two stages, no pose prior files:

1. Analytic IK on the model's rest skeleton, the BVH export's: a joint with several children (pelvis,
   spine3) gets the Kabsch rotation of its rest child offsets onto the observed ones; a joint with one
   child aims its bone with the twist taken from the body (:mod:`lsgan.export.aim`), so the twist about
   each bone is the one the bend planes, feet and hips and shoulders lines say, and never drifts.
2. Batched refinement in torch (L-BFGS, all frames at once) of the axis-angle poses, the translations and
   one shared set of betas: squared joint error through smplx's rigid chain, plus a temporal smoothness
   term, a pull towards the IK start (the twist about a bone is invisible to joint positions) and a small
   penalty on betas.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.body_model import NUM_BETAS, BodyModel
from lsgan.data.skeleton import NUM_JOINTS, PARENTS
from lsgan.export.bvh import joint_rotations
from lsgan.io import atomic_file

CM = 100.0  # joint errors enter the losses in centimetres, so 1 mm weighs 0.01 against the weights below
SMOOTH_WEIGHT = 1e-3
INIT_WEIGHT = 1e-4
BETA_WEIGHT = 1e-4


@dataclass(frozen=True)
class BodyFit:
    """Fitted parameters of one motion; ``poses`` in the model's full layout (joint j at ``3*j:3*j+3``)."""

    model_type: str
    gender: str
    poses: np.ndarray  # (T, 3*J) axis-angle: global orient, body, then jaw/eyes/hands (zeros)
    trans: np.ndarray  # (T,3) metres
    betas: np.ndarray  # (NUM_BETAS,)
    joints: np.ndarray  # (T,22,3) joints of the fitted body
    error_m: np.ndarray  # (T,) mean distance of the 22 fitted joints to the input, per frame
    max_error_m: float  # the largest single joint distance
    fps: float

    @property
    def mean_error_mm(self) -> float:
        return float(self.error_m.mean() * 1000.0)

    @property
    def max_joint_error_mm(self) -> float:
        return float(self.max_error_m * 1000.0)


def _rotvec(mats: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(mats.reshape(-1, 3, 3)).as_rotvec().reshape(mats.shape[:-2] + (3,))


def ik_start(joints: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Local rotations (T,22,3,3) posing the rest joints ``rest`` (>=22,3) like ``joints`` (stage 1): the BVH
    export's IK (:func:`lsgan.export.bvh.joint_rotations`), twists from the body."""
    offsets = np.zeros((NUM_JOINTS, 3))
    offsets[1:] = rest[1:NUM_JOINTS] - rest[list(PARENTS[1:])]
    return joint_rotations(joints, offsets)


def _torch_model(model: BodyModel, device: str):
    import torch

    t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    return (t(model.v_template), t(model.shapedirs), t(model.j_regressor),
            torch.as_tensor(model.parents, device=device))


def _posed_joints(pose, trans, betas, tensors):
    """Joints (N,J,3) of the body for axis-angle ``pose`` (N,J,3), ``trans`` (N,3), ``betas`` (B,)."""
    from smplx.lbs import batch_rigid_transform, batch_rodrigues

    v_template, shapedirs, j_regressor, parents = tensors
    rest = j_regressor @ (v_template + shapedirs[..., : betas.shape[0]] @ betas)  # (J,3)
    n, n_joints = pose.shape[:2]
    rot = batch_rodrigues(pose.reshape(-1, 3)).reshape(n, n_joints, 3, 3)
    posed, _ = batch_rigid_transform(rot, rest.expand(n, -1, -1).contiguous(), parents, dtype=pose.dtype)
    return posed + trans[:, None]


def _betas_from_bones(joints: np.ndarray, tensors, device: str):
    """Betas (B,) whose rest bone lengths best match the mean observed ones (L-BFGS, a few ms)."""
    import torch

    v_template, shapedirs, j_regressor, _ = tensors
    parents = list(PARENTS[1:])
    observed = np.linalg.norm(joints[:, 1:] - joints[:, parents], axis=-1).mean(axis=0)
    lengths = torch.as_tensor(observed, dtype=torch.float32, device=device)
    betas = torch.zeros(shapedirs.shape[-1], dtype=torch.float32, device=device, requires_grad=True)
    optimiser = torch.optim.LBFGS([betas], max_iter=50, line_search_fn="strong_wolfe")

    def closure():
        optimiser.zero_grad()
        rest = (j_regressor @ (v_template + shapedirs @ betas))[:NUM_JOINTS]
        bone = (rest[1:] - rest[parents]).norm(dim=-1)
        loss = (((bone - lengths) * CM) ** 2).sum() + BETA_WEIGHT * (betas ** 2).sum()
        loss.backward()
        return loss

    optimiser.step(closure)
    return betas.detach()


def fit_body(joints: np.ndarray, model: BodyModel, *, iterations: int = 100,
             fit_betas: bool = True, fps: float = 20.0, device: str = "cpu", seed: int = 0) -> BodyFit:
    """Fit ``model`` to joint positions (T,22,3) in metres; deterministic for a given ``seed``."""
    import torch

    target_np = np.asarray(joints, dtype=np.float64)
    if target_np.ndim != 3 or target_np.shape[1:] != (NUM_JOINTS, 3) or len(target_np) == 0:
        raise ValueError(f"joints must be (T,{NUM_JOINTS},3) with T > 0, got {target_np.shape}")
    if not np.isfinite(target_np).all():
        raise ValueError("joints hold NaN or infinite values")
    torch.manual_seed(seed)
    frames, n_joints = len(target_np), model.num_joints
    tensors = _torch_model(model, device)
    f32 = dict(dtype=torch.float32, device=device)
    betas = _betas_from_bones(target_np, tensors, device) if fit_betas else \
        torch.zeros(model.shapedirs.shape[-1], **f32)
    rest = model.rest_joints(betas.cpu().numpy())
    init = _rotvec(ik_start(target_np, rest))
    target = torch.as_tensor(target_np, **f32)
    start = torch.as_tensor(init, **f32)
    body = start.clone().requires_grad_(True)
    trans = torch.as_tensor(target_np[:, 0] - rest[0], **f32).requires_grad_(True)
    betas.requires_grad_(fit_betas)
    rest_pose = torch.zeros(frames, n_joints - NUM_JOINTS, 3, **f32)
    params = [body, trans] + ([betas] if fit_betas else [])
    optimiser = torch.optim.LBFGS(params, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-9, tolerance_change=1e-12)

    def predict():
        return _posed_joints(torch.cat([body, rest_pose], dim=1), trans, betas, tensors)[:, :NUM_JOINTS]

    def closure():
        optimiser.zero_grad()
        loss = (((predict() - target) * CM) ** 2).sum(-1).mean()
        if frames > 1:
            loss = loss + SMOOTH_WEIGHT * ((body[1:] - body[:-1]) ** 2).sum(-1).mean()
        loss = loss + INIT_WEIGHT * ((body - start) ** 2).sum(-1).mean() + BETA_WEIGHT * (betas ** 2).sum()
        loss.backward()
        return loss

    optimiser.step(closure)
    with torch.no_grad():
        fitted = predict().double()
        per_joint = (fitted - target.double()).norm(dim=-1)
    poses = np.zeros((frames, n_joints, 3), dtype=np.float32)
    poses[:, :NUM_JOINTS] = body.detach().cpu().numpy()
    beta_out = np.zeros(NUM_BETAS, dtype=np.float32)
    beta_out[: betas.shape[0]] = betas.detach().cpu().numpy()
    return BodyFit(
        model_type=model.model_type, gender=model.gender, poses=poses.reshape(frames, -1),
        trans=trans.detach().cpu().numpy().astype(np.float32), betas=beta_out,
        joints=fitted.cpu().numpy().astype(np.float32), error_m=per_joint.mean(-1).cpu().numpy(),
        fps=float(fps), max_error_m=float(per_joint.max()),
    )


def body_joints(fit: BodyFit, model: BodyModel) -> np.ndarray:
    """All J joints (T,J,3) of ``model`` posed by ``fit`` (the skeleton a skinned export animates)."""
    import torch

    tensors = _torch_model(model, "cpu")
    with torch.no_grad():
        pose = torch.as_tensor(fit.poses, dtype=torch.float32).reshape(len(fit.poses), -1, 3)
        out = _posed_joints(pose, torch.as_tensor(fit.trans), torch.as_tensor(fit.betas), tensors)
    return out.numpy()


def write_fit_npz(path: str | Path, fit: BodyFit) -> Path:
    """Write the fitted parameters as an AMASS-style ``.npz`` (Y up, not AMASS's Z up), atomically.

    Keys: ``poses`` (T,3J), ``trans`` (T,3), ``betas`` (10,), ``gender``, ``surface_model_type``,
    ``mocap_framerate``, ``up_axis`` ("Y") and the fit's ``joints`` (T,22,3) and ``fit_error_m`` (T,).
    Strings are stored as plain unicode arrays, so ``np.load(..., allow_pickle=False)`` reads everything.
    """
    path = Path(path)
    with atomic_file(path) as fh:
        np.savez(fh, poses=fit.poses, trans=fit.trans, betas=fit.betas, gender=np.str_(fit.gender),
                 surface_model_type=np.str_(fit.model_type), mocap_framerate=np.float64(fit.fps),
                 up_axis=np.str_("Y"), joints=fit.joints, fit_error_m=fit.error_m.astype(np.float32))
    return path
