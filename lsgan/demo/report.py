"""What a demo run returns and prints: where everything is, the metrics and the stage timings."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from lsgan.demo.markers import STAGES, StageRecord
from lsgan.demo.settings import DemoSettings

@dataclass
class DemoResult:
    """Where everything is, the metrics and the stage timings of one ``run_demo``."""

    out: Path
    settings: DemoSettings
    data: Path
    cache: Path
    vae: Path
    gan: Path
    evaluator: Path
    metrics_json: Path
    metrics_md: Path
    motions: Path
    glb: list[Path]
    gif: list[Path]
    summary: Path
    metrics: dict  # row -> column -> {"mean", "ci95"}
    table: str  # the metrics as markdown
    stages: list[StageRecord] = field(default_factory=list)
    seconds: float = 0.0  # this run's wall time

    def report(self) -> str:
        """What ``lsgan demo`` prints at the end: the files, the table and what it is (not)."""
        s = self.settings
        rel = lambda p: os.path.relpath(p) if not os.path.relpath(p).startswith("..") else str(p)  # noqa: E731
        lines = [f"lsgan demo: done ({self.seconds:.0f} s this run; the stages took "
                 f"{sum(st.seconds for st in self.stages):.0f} s in all; scale {s.scale:g})", "",
                 "Stages:"]
        for st in self.stages:
            lines.append(f"  [{st.index}/{len(STAGES)}] {st.name:<16} {st.seconds:7.1f} s  {st.status:<8} {st.output}")
        lines += [
            "", "Files:",
            f"  data (synthetic clips)   {rel(self.data)}",
            f"  VAE / GAN / evaluator    {rel(self.vae)}  {rel(self.gan)}  {rel(self.evaluator)}",
            f"  motions (.npy)           {rel(self.motions)}",
            f"  animated GLB             {rel(self.glb[0].parent)}/ ({len(self.glb)} files: Blender, three.js, "
            "any glTF viewer)",
            f"  GIF previews             {rel(self.gif[0].parent)}/ ({len(self.gif)} files)",
            f"  metrics                  {rel(self.metrics_md)}  {rel(self.metrics_json)}",
            f"  summary                  {rel(self.summary)}",
            "", f"Text-to-motion on the synthetic test split (our own evaluator; {s.reduced}):", "", self.table, "",
            "R-precision by chance: top-1 0.031, top-2 0.063, top-3 0.094 (groups of 32). The data are synthetic and",
            "the evaluator is ours: these numbers are not comparable with published HumanML3D tables.",
        ]
        return "\n".join(lines)
