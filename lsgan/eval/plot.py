"""t-SNE of real and generated latents coloured by action (the paper's Figure 4): ``lsgan plot-latents``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from lsgan.io import atomic_file


def latent_points(cache: str | Path, model: str | Path, *, split: str = "test", per_class: int = 50,
                  seed: int = 0, device: str = "auto", steps: int | None = None, guidance: float | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Real latent means of up to ``per_class`` labelled clips per action and one generated latent per clip
    (conditioned on the clip's first caption, or its action for action models).

    Returns (latents (2N,Z), action index (2N,), is_generated (2N,) bool, action names).
    """
    from lsgan.generate import Request, sample_latents
    from lsgan.models.cache import read_latent_cache

    data = read_latent_cache(cache)
    rng = np.random.default_rng(seed)
    chosen = []
    for a in range(len(data.action_names)):
        idx = np.flatnonzero((data.actions == a) & (data.splits == split))
        chosen += list(rng.permutation(idx)[:per_class])
    if not chosen:
        raise ValueError(f"{cache}: no {split} clips with action labels; the plot colours latents by action")
    chosen = np.array(sorted(chosen))
    first_caption = {}
    for m, clip in enumerate(data.caption_clip):
        first_caption.setdefault(int(clip), data.caption_text[m])
    requests = [Request(text=first_caption.get(int(i)), action=data.action_names[data.actions[i]],
                        frames=int(data.lengths[i])) for i in chosen]
    fake = sample_latents(model, requests, seed=seed, device=device, steps=steps, guidance=guidance)
    real = data.mu[chosen]
    labels = np.concatenate([data.actions[chosen], data.actions[chosen]])
    generated = np.concatenate([np.zeros(len(chosen), bool), np.ones(len(chosen), bool)])
    return np.concatenate([real, fake]), labels, generated, list(data.action_names)


def tsne_2d(points: np.ndarray, *, seed: int = 0, perplexity: float = 30.0) -> np.ndarray:
    """(N,2) t-SNE embedding (scikit-learn, PCA initialisation, deterministic for a seed)."""
    from sklearn.manifold import TSNE

    perplexity = min(perplexity, max(2.0, (len(points) - 1) / 3))
    return TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(
        np.asarray(points, dtype=np.float64))


def plot_latents(cache: str | Path, model: str | Path, out: str | Path, *, split: str = "test",
                 per_class: int = 50, seed: int = 0, device: str = "auto", steps: int | None = None,
                 guidance: float | None = None, title: str | None = None, force: bool = False) -> Path:
    """Write the PNG: real latents as dots, generated ones as crosses, one colour per action.

    An existing ``out`` is refused unless ``force`` (and then only replaced when lsgan wrote it).
    """
    from lsgan import outputs

    outputs.claim_file(out, force=force, inputs=[cache, model])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points, labels, generated, names = latent_points(cache, model, split=split, per_class=per_class, seed=seed,
                                                     device=device, steps=steps, guidance=guidance)
    xy = tsne_2d(points, seed=seed)
    colours = plt.get_cmap("tab20" if len(names) > 10 else "tab10")
    fig, ax = plt.subplots(figsize=(8, 7), dpi=120)
    for a, name in enumerate(names):
        for fake, marker in ((False, "o"), (True, "x")):
            sel = (labels == a) & (generated == fake)
            if sel.any():
                ax.scatter(xy[sel, 0], xy[sel, 1], s=14 if fake else 10, marker=marker, color=colours(a % 20),
                           alpha=0.85, label=name if not fake else None)
    ax.set_title(title or f"t-SNE of latents: real (o) and generated (x), {Path(str(model)).name}")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.legend(loc="best", fontsize=7, markerscale=1.5, frameon=False)
    fig.tight_layout()
    out = Path(out)
    with atomic_file(out) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return out
