"""Replay a training step as one CUDA graph.

A latent GAN's step is many small operations: deep-wgan-gp's five critic updates (each with a double backward for
the gradient penalty) and one generator update each launch hundreds of kernels on a batch of 64 latents, so on a
GPU the step is bound by the host launching kernels, not by the GPU running them. Captured once and replayed, the
whole step is one launch.

What makes the replay the same training as the eager steps:
- The step's random draws come from the loop's per-step generator (:class:`lsgan.train.loop.SeededSteps`), which
  is registered with the graph: every replay reads the seed the loop has just set and starts at its offset 0,
  as an eager step does, so each step draws what it would draw eagerly.
- The optimisers are built ``capturable`` on CUDA in both modes (:func:`optimizer_options`), so the eager steps
  and the replays run the same update kernels and a run may switch modes on ``--resume``.
- The first ``warmup`` steps run eagerly on a side stream (the optimisers create their state, the libraries
  their workspaces), and the graph is captured on the step after them, so a resumed run captures after its
  checkpoint is loaded.
- The step's outputs live in the graph's memory; each replay hands back copies, so the loop's pending scalars
  are not overwritten by the next replay.
"""
from __future__ import annotations

from typing import Callable

import torch

Step = Callable[[torch.Generator], dict[str, torch.Tensor]]


def use_cuda_graph(wanted: bool, device: torch.device, distributed: bool) -> bool:
    """Whether a step is replayed as a CUDA graph: asked for, on a CUDA device, and in a single process (a
    DistributedDataParallel step synchronises with its peers, which a plain capture does not cover)."""
    return wanted and device.type == "cuda" and not distributed


def optimizer_options(device: torch.device) -> dict:
    """The optimiser arguments that let a step be captured: capturable on CUDA (in both modes, so that graphs on or
    off give the same updates), torch's defaults elsewhere."""
    return {"capturable": True} if device.type == "cuda" else {}


class GraphedStep:
    """``step(generator) -> {name: scalar tensor}``, eager for the first ``warmup`` calls, then captured once and
    replayed."""

    def __init__(self, step: Step, warmup: int = 3) -> None:
        if warmup < 1:
            raise ValueError("a step needs at least one eager warm-up call before its capture")
        self.step, self.warmup, self.calls = step, warmup, 0
        self.graph: torch.cuda.CUDAGraph | None = None
        self.out: dict[str, torch.Tensor] = {}
        self.side: torch.cuda.Stream | None = None
        self.generator: torch.Generator | None = None

    @property
    def captured(self) -> bool:
        return self.graph is not None

    def __call__(self, g: torch.Generator) -> dict[str, torch.Tensor]:
        if self.graph is None:
            if self.calls < self.warmup:
                self.calls += 1
                return self._eager(g)
            self._capture(g)
        if g is not self.generator:
            raise ValueError("a captured step replays the draws of the generator it was captured with")
        self.graph.replay()
        return {k: v.clone() for k, v in self.out.items()}

    def _eager(self, g: torch.Generator) -> dict[str, torch.Tensor]:
        """One eager step on a side stream (warm-up before a capture must not run on the capturing stream)."""
        self.side = self.side or torch.cuda.Stream()
        self.side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self.side):
            out = self.step(g)
        torch.cuda.current_stream().wait_stream(self.side)
        return out

    def _capture(self, g: torch.Generator) -> None:
        """Record the step (nothing runs: the replay that follows takes it)."""
        graph = torch.cuda.CUDAGraph()
        graph.register_generator_state(g)
        with torch.cuda.graph(graph):
            self.out = self.step(g)
        self.graph, self.generator = graph, g
