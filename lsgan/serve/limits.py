"""The bounds ``lsgan serve`` holds every request to, in one place (each is a command-line option)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

MAX_SEED = 2**53 - 1  # the largest integer a JavaScript client can send back exactly
TRAINED_FRAMES = 196  # HumanML3D's longest clip: the default bound of a model that could decode longer
MAX_WAIT_S = 3600.0  # the longest any timeout may be: a larger one (or inf) would in effect switch its bound off


@dataclass(frozen=True)
class Limits:
    """What one request may ask and how much the server takes on at once."""

    max_text_chars: int = 500  # characters of a prompt (MiniLM reads at most 256 tokens of it anyway)
    min_frames: int = 4  # `lsgan generate` refuses fewer too
    max_frames: int | None = None  # None: the model's own maximum (its VAE's positional table), at most 196
    default_frames: int | None = None  # None: 120, or max_frames when less
    max_num: int = 8  # motions per request
    max_control_num: int = 2  # motions per request with constraints (path, keyframes, continue_from)
    max_body_bytes: int = 16384  # of a request body
    max_in_flight: int = 64  # requests admitted and not yet answered; more get 503 with Retry-After
    timeout_s: float = 10.0  # per request, from admission to its motions; then 503
    gather_ms: float = 1.0  # how long a pass waits for more requests after the first one
    max_batch: int = 8  # motions in one engine pass (two engines on two cores: p99 200 against 230 ms at 16)
    store_size: int = 256  # motions kept for download (least recently used are dropped)
    # HTTP itself (lsgan.serve.protocol; browsers and client libraries stay far below these)
    max_line_bytes: int = 8192  # request target (path and query); more gets 414
    max_header_bytes: int = 65536  # request line and headers together; more gets 431
    max_headers: int = 100  # header lines; more gets 431
    header_timeout_s: float = 10.0  # for a request's head to arrive, from its first byte or the connection; 408
    body_timeout_s: float = 10.0  # for its body to arrive after the head; 408
    keep_alive_s: float = 5.0  # an idle keep-alive connection is closed after this (uvicorn's timeout_keep_alive)
    max_connections: int = 1024  # open at once; past it the longest-waiting idle or slow one is closed

    def checked(self, model_max_frames: int) -> Limits:
        """These limits with the model's frame bounds filled in; a ValueError when they contradict each other or
        the model."""
        if self.max_frames is None:
            self = replace(self, max_frames=min(TRAINED_FRAMES, model_max_frames))
        if self.default_frames is None:
            self = replace(self, default_frames=min(120, self.max_frames))
        problems = [f"{name} {rule}" for name, ok, rule in (
            ("max_text_chars", self.max_text_chars >= 1, "at least 1"),
            ("min_frames", 1 <= self.min_frames <= self.max_frames, "1 to max_frames"),
            ("max_num", self.max_num >= 1, "at least 1"),
            ("max_control_num", self.max_control_num >= 1, "at least 1"),
            ("max_body_bytes", self.max_body_bytes >= 64, "at least 64"),
            ("max_in_flight", self.max_in_flight >= 1, "at least 1"),
            ("timeout_s", 0 < self.timeout_s <= MAX_WAIT_S, f"above 0, at most {MAX_WAIT_S:g}"),
            ("gather_ms", 0 <= self.gather_ms <= 1000, "0 to 1000"),
            ("max_batch", self.max_batch >= self.max_num, "at least max_num"),
            ("store_size", self.store_size >= self.max_num, "at least max_num"),
            ("max_line_bytes", 64 <= self.max_line_bytes <= self.max_header_bytes, "64 to max_header_bytes"),
            ("max_header_bytes", self.max_header_bytes >= 1024, "at least 1024"),
            ("max_headers", self.max_headers >= 8, "at least 8"),
            ("header_timeout_s", 0 < self.header_timeout_s <= MAX_WAIT_S, f"above 0, at most {MAX_WAIT_S:g}"),
            ("body_timeout_s", 0 < self.body_timeout_s <= MAX_WAIT_S, f"above 0, at most {MAX_WAIT_S:g}"),
            ("keep_alive_s", 0 < self.keep_alive_s <= MAX_WAIT_S, f"above 0, at most {MAX_WAIT_S:g}"),
            ("max_connections", self.max_connections >= 1, "at least 1"),
        ) if not ok]
        if problems:
            raise ValueError(f"inconsistent limits: {'; '.join(problems)} ({self.describe()})")
        if self.max_frames > model_max_frames:
            raise ValueError(f"max frames {self.max_frames} is more than this model decodes ({model_max_frames}, "
                             "its VAE's positional table)")
        if not self.min_frames <= self.default_frames <= self.max_frames:
            raise ValueError(f"default frames {self.default_frames} is outside {self.min_frames}..{self.max_frames}")
        return self

    def describe(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in asdict(self).items())

    def as_dict(self) -> dict:
        return asdict(self)
