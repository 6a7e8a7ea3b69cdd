"""The JSON shapes of the API (pydantic models: they also make the OpenAPI schema at /openapi.json)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from lsgan.serve.limits import MAX_SEED


class GenerateRequest(BaseModel):
    """Give exactly one of ``text`` (text-conditioned models) and ``action`` (action-conditioned ones)."""

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


class Timings(BaseModel):
    queue: float = Field(description="ms waiting for the engine (gathering window included)")
    text: float = Field(description="ms of text encoding, for the whole pass")
    generator: float = Field(description="ms of the generator pass, for the whole pass")
    decoder: float = Field(description="ms of VAE decoding, for the whole pass")
    total: float = Field(description="ms from the request's arrival to its answer")


class GenerateResponse(BaseModel):
    motions: list[MotionOut]
    seed: int
    fps: float
    timings_ms: Timings
    batch_size: int = Field(description="Motions that shared this engine pass (this request's and others').")


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
    skeleton: Skeleton


class ErrorOut(BaseModel):
    error: str = Field(description="One line saying what was wrong.")


class Health(BaseModel):
    status: str
