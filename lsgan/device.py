"""Which torch device a command runs on: one helper below every layer that computes (models, training, evaluation,
generation), so that none of them reaches into another for it."""
from __future__ import annotations

import torch


def pick_device(name: str = "auto") -> torch.device:
    """'auto' -> cuda when available, else cpu; otherwise the named device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for, but torch sees no CUDA device")
    return device


def as_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch.device (the models' constructors take either)."""
    return device if isinstance(device, torch.device) else torch.device(device)
