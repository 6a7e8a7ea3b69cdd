"""The JSON shapes of the API (pydantic models: they also make the OpenAPI schema at /openapi.json)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from lsgan.serve.limits import MAX_SEED


class Keyframe(BaseModel):
    """Joints to hit on one frame, in the motion's own frame (metres, Y up; the root starts at the origin facing +z)."""

    model_config = ConfigDict(strict=True, extra="forbid")

    frame: int = Field(description="0 .. frames - 1")
    joints: dict[str, list[float | None]] | list[list[float]] = Field(
        description="Some joints by name or index, {\"left_wrist\": [x, y, z]} (null leaves a coordinate free: "
                    "{\"head\": [null, 1.7, null]}), or all 22 as [[x, y, z], ...] in HumanML3D's order (GET /v1/info: "
                    "skeleton.names).")


class GenerateRequest(BaseModel):
    """Give exactly one of ``text`` (text-conditioned models) and ``action`` (action-conditioned ones). Constraints
    (docs/control.md): ``path`` and ``keyframes``, or ``continue_from`` alone."""

    model_config = ConfigDict(strict=True, extra="forbid", json_schema_extra={
        "examples": [{"text": "a person walks forward", "frames": 120, "num": 1, "seed": 7}]})

    text: str | None = Field(None, description="The prompt: printable text, no control characters; at most "
                             "limits.max_text_chars characters (GET /v1/info).")
    action: str | None = Field(None, description="An action label of the model (GET /v1/info: actions).")
    frames: int | None = Field(None, description="Length at 20 fps, limits.min_frames..limits.max_frames "
                               "(default: default_frames).")
    num: int = Field(1, description="Motions to make, 1..limits.max_num; motion k uses the k-th draw of the seed.")
    seed: int | None = Field(None, ge=0, le=MAX_SEED, description="The same seed, prompt and length give the same "
                             "motions, alone or batched with other requests. Default: drawn and returned.")
    path: list[list[float]] | None = Field(None, description="A root path on the ground, shifted to start where the "
                                           "motion starts: rows of [t, x, z] waypoints (seconds from 0, at least a "
                                           "frame apart; linear between them) or [x, z] per frame from frame 0.")
    facing: bool = Field(False, description="With a path: the root also faces along it wherever it moves.")
    keyframes: list[Keyframe] | None = Field(None, description="Joints to hit on given frames (one entry per frame).")
    continue_from: str | None = Field(None, description="The id of an earlier motion (still in the store): the new "
                                      "one starts with its last 5 frames and stands where it ends.")


class MotionUrls(BaseModel):
    glb: str = Field(description="Animated skeleton, glTF 2.0 binary (Y up, metres).")
    bvh: str = Field(description="BVH, 22-joint skeleton, centimetres.")
    npy: str = Field(description="The joints as a NumPy .npy array (T, 22, 3) float32, metres, exact.")


class MotionOut(BaseModel):
    id: str = Field(description="Download id; kept while the server's store holds the motion (LRU).")
    frames: int
    joints: list[list[list[float]]] = Field(description="(frames, 22, 3) positions in metres, Y up, rounded to "
                                            "0.1 mm (the .npy download is exact).")
    urls: MotionUrls
    control: dict | None = Field(None, description="With constraints: how far this motion is from them, metres "
                                 "(path_m, keyframes_m) and m/s (seam_velocity_m_s), each {mean, max}.")


class Timings(BaseModel):
    queue: float = Field(description="ms waiting for the engine (gathering window included)")
    text: float = Field(description="ms of text encoding, for the whole pass")
    generator: float = Field(description="ms of the generator pass, for the whole pass")
    decoder: float = Field(description="ms of VAE decoding, for the whole pass")
    control: float = Field(description="ms of meeting constraints (optimisation and closing), for the whole pass")
    total: float = Field(description="ms from the request's arrival to its answer")


class GenerateResponse(BaseModel):
    motions: list[MotionOut]
    seed: int
    fps: float
    timings_ms: Timings
    batch_size: int = Field(description="Motions that shared this engine pass (this request's and others').")
    placement: dict | None = Field(None, description="With continue_from: where the motions stand, turned by "
                                   "yaw_rad about +y and moved by (x_m, 0, z_m) from their own frame.")


class Skeleton(BaseModel):
    names: list[str]
    parents: list[int] = Field(description="Parent joint index per joint; -1 for the root.")
    chains: list[list[int]] = Field(description="Joint indices along each drawn chain (legs, spine, arms).")
    chain_colours: list[str] = Field(description="#rrggbb per chain: left blue, right red, spine grey.")


class Info(BaseModel):
    condition: str = Field(description="text or action")
    actions: list[str]
    fps: float
    max_frames: int
    default_frames: int
    min_frames: int
    limits: dict
    auth: bool = Field(description="Whether /v1 needs Authorization: Bearer KEY (or X-API-Key).")
    control: dict | None = Field(None, description="Whether the model takes constraints: null, or {steers: whether "
                                 "they are approached by optimisation before being met (the torch backend), "
                                 "max_speed_m_s: the fastest root a path may ask for}.")
    skeleton: Skeleton


class ErrorOut(BaseModel):
    error: str = Field(description="One line saying what was wrong.")


class Health(BaseModel):
    status: str
