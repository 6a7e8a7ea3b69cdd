"""A POST /v1/generate body -> an engine :class:`Item`, or an :class:`ApiError` with a one-line reason."""
from __future__ import annotations

import secrets

from pydantic import ValidationError

from lsgan.generation import text_problem
from lsgan.serve.engine import Engine, Item
from lsgan.serve.limits import Limits
from lsgan.serve.schemas import GenerateRequest, Keyframe

FIELDS = ", ".join(GenerateRequest.model_fields)
KEYFRAME_FIELDS = ", ".join(Keyframe.model_fields)
DRAWN_SEEDS = 2**31  # a seed the server draws is below this


class ApiError(Exception):
    """An answer other than 200: status, one-line reason, extra headers."""

    def __init__(self, status: int, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.message, self.headers = status, message, headers or {}


JSON_TYPES = {"NoneType": "null", "str": "string", "dict": "object", "list": "array", "int": "integer",
              "float": "number", "bool": "boolean"}


def json_type(value) -> str:
    """The JSON name of a parsed value's type."""
    return JSON_TYPES.get(type(value).__name__, type(value).__name__)


def short(value, limit: int = 40) -> str:
    """``repr(value)`` cut to ``limit`` characters, for echoing a client's value in a message."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def parse_json(body: bytes) -> dict:
    """The body as a JSON object; 400 for malformed JSON (NaN, Infinity and a key given twice included), 422 for
    another type."""
    from lsgan.jsonread import strict_json

    if not body.strip():
        raise ApiError(400, "empty body: send a JSON object such as {\"text\": \"a person walks forward\"}")
    try:
        obj = strict_json(body)
    except ValueError as e:  # JSONDecodeError, UnicodeDecodeError (not UTF-8), NaN / Infinity, a key twice, nesting
        raise ApiError(400, f"malformed JSON: {str(e).splitlines()[0][:200]}") from None
    if not isinstance(obj, dict):
        raise ApiError(422, f"the body must be a JSON object such as {{\"text\": \"a person walks\"}}, "
                            f"not a {json_type(obj)}")
    return obj


def _validation_message(error: ValidationError) -> str:
    """pydantic's first error as one line: the field, then what is wrong with it."""
    e = error.errors()[0]
    where = ".".join(str(p) for p in e["loc"] if "[" not in str(p)) or "body"  # not pydantic's union members
    if e["type"] == "extra_forbidden":
        fields = FIELDS if len(e["loc"]) == 1 else f"{KEYFRAME_FIELDS} (of a keyframe)"
        return f"{where}: unknown field (the fields are {fields})"
    got = json_type(e["input"]) if "input" in e else ""
    msg = e["msg"][0].lower() + e["msg"][1:]
    return f"{where}: {msg}" + (f", got {got}" if got and e["type"].endswith("_type") else "")


def check_text(text: str, limits: Limits) -> str:
    """The prompt, stripped; refused when too long or no prompt (:func:`lsgan.generation.text_problem`)."""
    if problem := text_problem(text):
        raise ApiError(422, problem)
    stripped = text.strip()
    if len(text) > limits.max_text_chars:
        raise ApiError(422, f"text is {len(text)} characters long; the limit is {limits.max_text_chars}")
    return stripped


def to_item(obj: dict, engine: Engine, limits: Limits, lookup=lambda key: None) -> Item:
    """The request as an engine item, every field checked against the model and the limits; ``lookup(id)``: the
    joints (T, 22, 3) of a stored motion, or None (for ``continue_from``)."""
    try:
        req = GenerateRequest.model_validate(obj)
    except ValidationError as e:
        raise ApiError(422, _validation_message(e)) from None
    if (req.text is None) == (req.action is None):
        raise ApiError(422, "give exactly one of \"text\" and \"action\""
                       f" (this model is {engine.condition}-conditioned)")
    if engine.condition == "text" and req.text is None:
        raise ApiError(422, "this model is conditioned on text: give \"text\", not \"action\"")
    if engine.condition == "action" and req.action is None:
        raise ApiError(422, f"this model is conditioned on actions: give \"action\", one of {engine.actions}")
    text = check_text(req.text, limits) if req.text is not None else None
    if req.action is not None and req.action not in engine.actions:
        raise ApiError(422, f"unknown action {short(req.action)}; this model knows {engine.actions}")
    frames = limits.default_frames if req.frames is None else req.frames
    if not limits.min_frames <= frames <= limits.max_frames:
        raise ApiError(422, f"frames must be {limits.min_frames} to {limits.max_frames}, got {short(frames)}")
    if not 1 <= req.num <= limits.max_num:
        raise ApiError(422, f"num must be 1 to {limits.max_num}, got {short(req.num)}")
    seed = secrets.randbelow(DRAWN_SEEDS) if req.seed is None else req.seed
    control, placement = control_of(req, engine, frames, lookup)
    most = min(limits.max_control_num, limits.max_num)
    if control is not None and req.num > most:
        raise ApiError(422, f"num must be 1 to {most} with constraints (each motion is optimised), got {short(req.num)}")
    return Item(text=text, action=req.action, frames=frames, num=req.num, seed=seed, control=control,
                placement=placement)


def control_of(req: GenerateRequest, engine: Engine, frames: int, lookup) -> tuple[dict | None, tuple | None]:
    """The request's constraints as a record for the engine (:mod:`lsgan.constraints`), and a continuation's
    placement; (None, None) without constraints. The file readers' rules, then the model's reach."""
    import numpy as np

    from lsgan.constraints import Constraints, check_reach, continuing, json_rows, path_from_rows, pose_from_json

    given = [name for name in ("path", "keyframes", "continue_from") if getattr(req, name) is not None]
    if req.facing and req.path is None:
        raise ApiError(422, "facing: it turns the root along a path; send a path")
    if not given:
        return None, None
    if req.keyframes == []:
        raise ApiError(422, "keyframes: an empty list; give at least one keyframe, or leave the field out")
    if engine.reach is None:
        raise ApiError(422, f"{given[0]}: this server's model does not take constraints")
    if req.continue_from is not None and len(given) > 1:
        raise ApiError(422, "continue_from sets every constraint itself: send it without path and keyframes")
    placement = None
    with np.errstate(all="ignore"):  # a huge number is refused by its check, not warned about by numpy
        if req.continue_from is not None:
            joints = lookup(req.continue_from)
            if joints is None:
                raise ApiError(422, f"continue_from: no motion {short(req.continue_from)} (an unknown id, or one "
                                    "dropped from the store)")
            c, place = _refused("continue_from", lambda: continuing(joints, frames))
            placement = (place.yaw, place.x, place.z)
        else:
            path = None if req.path is None else _refused("path", lambda: path_from_rows(json_rows(req.path), frames))
            poses = {}
            for i, k in enumerate(req.keyframes or ()):
                if k.frame in poses:
                    raise ApiError(422, f"keyframes[{i}]: a second keyframe for frame {k.frame}")
                poses[k.frame] = _refused(f"keyframes[{i}]", lambda k=k: pose_from_json(k.joints))
                _refused(f"keyframes[{i}]", lambda k=k: Constraints(frames, keyframes={k.frame: poses[k.frame]}))
            c = _refused("constraints", lambda: Constraints(frames, path=path, keyframes=poses, facing=req.facing))
        _refused(given[0] if len(given) == 1 else "constraints",
                 lambda: check_reach(c, engine.reach["speed"], np.asarray(engine.reach["skeleton"])))
    return c.record(), placement


def _refused(where: str, make):
    """``make()``, its ValueError a 422 naming ``where``."""
    try:
        return make()
    except ValueError as e:
        raise ApiError(422, f"{where}: {str(e).splitlines()[0]}") from None
