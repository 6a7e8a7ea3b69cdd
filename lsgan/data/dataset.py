"""A torch Dataset over shards with the HumanML3D training protocol, and a length-bucketing batch sampler.

Protocol (as the T2M/MLD loaders): every caption with a time span becomes its own window of the clip,
its frames by T2M's rule (:func:`lsgan.data.captions.span_frames`); whole-clip captions share the full
clip. Windows shorter than ``min_frames`` are dropped; longer than ``max_frames`` are randomly cropped
(``crop_long``; the original loaders drop clips of 200+ frames). Each draw picks one caption at random,
rounds the length down to a multiple of ``unit_length`` (one unit shorter with probability 1/3), takes a
random crop of that length and normalises it with Mean/Std.
"""
from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from lsgan.data.captions import span_frames
from lsgan.data.shards import Shard


@dataclass(frozen=True)
class Window:
    shard: int
    clip: int
    start: int
    stop: int
    captions: tuple[int, ...]  # indices into the clip's caption list; empty = no caption


class MotionDataset(Dataset):
    """Windows of the clips of one split of one or more shards.

    Items are dicts: ``motion`` (L,263) float32 tensor (normalised), ``length``, ``caption``, ``tokens``,
    ``action`` (int, -1 none), ``name``. Use :func:`collate` to batch them.
    """

    def __init__(
        self,
        shards: str | os.PathLike | Sequence[str | os.PathLike],
        split: str | None = "train",
        *,
        min_frames: int = 40,
        max_frames: int = 196,
        unit_length: int = 4,
        crop_long: bool = True,
        normalize: bool = True,
        mean: np.ndarray | None = None,
        std: np.ndarray | None = None,
        require_captions: bool = False,
        in_memory: bool = False,
    ) -> None:
        paths = [shards] if isinstance(shards, (str, os.PathLike)) else list(shards)
        if min_frames > max_frames:
            raise ValueError(f"min_frames ({min_frames}) > max_frames ({max_frames})")
        self.paths = [os.fspath(p) for p in paths]
        self.min_frames, self.max_frames, self.unit_length = min_frames, max_frames, unit_length
        self.crop_long, self.normalize, self.in_memory = crop_long, normalize, in_memory
        self.windows: list[Window] = []
        self.captions: list[list] = []  # per shard: per clip: captions
        self.names: list[list[str]] = []
        self.actions: list[np.ndarray] = []
        self.action_names: list[str] = []
        for s, path in enumerate(self.paths):
            with Shard(path) as shard:
                if s == 0:
                    self.action_names = shard.action_names
                    shard_mean, shard_std = shard.mean, shard.std
                elif shard.action_names != self.action_names:
                    raise ValueError(f"{path}: its action labels differ from those of {self.paths[0]}")
                caps = [shard.captions(i) for i in range(len(shard))]
                self.captions.append(caps)
                self.names.append(shard.names)
                self.actions.append(shard.actions)
                for i in shard.indices(split):
                    self.windows += self._windows(s, int(i), int(shard.lengths[i]), caps[i], require_captions)
        self.mean = np.asarray(shard_mean if mean is None else mean, np.float32)
        self.std = np.asarray(shard_std if std is None else std, np.float32)
        self._open: dict[int, Shard] = {}
        self._pid = os.getpid()

    def _windows(self, s: int, i: int, length: int, caps: list, require_captions: bool) -> list[Window]:
        """The clip's windows: whole-clip captions share one, each time span is its own (T2M's frame rule)."""
        frames = [span_frames(c.start, c.end, length) for c in caps]
        whole = tuple(k for k, span in enumerate(frames) if span is None)
        spans = [(k, span) for k, span in enumerate(frames) if span is not None]
        out: list[Window] = []
        if whole or not (spans or require_captions):
            out.append(Window(s, i, 0, length, whole))
        out += [Window(s, i, a, b, (k,)) for k, (a, b) in spans]
        keep = []
        for w in out:
            n = w.stop - w.start
            if n < max(self.min_frames, 1) or (n > self.max_frames and not self.crop_long):
                continue
            keep.append(w)
        return keep

    def __len__(self) -> int:
        return len(self.windows)

    def lengths(self) -> np.ndarray:
        """The length each window is drawn at before random shortening (for bucketing)."""
        return np.array([min(w.stop - w.start, self.max_frames) for w in self.windows])

    def _shard(self, s: int) -> Shard:
        if os.getpid() != self._pid:  # a DataLoader worker: h5py handles must not cross a fork
            self._open, self._pid = {}, os.getpid()
        if s not in self._open:
            self._open[s] = Shard(self.paths[s], in_memory=self.in_memory)
        return self._open[s]

    def draw(self, index: int) -> tuple[int, int, int]:
        """Window ``index`` as one draw of the protocol makes it: (frames, first frame in its clip, caption or -1).

        Up to three draws from torch's global RNG, always in this order (length, crop, caption), so that items and
        gathered batches (:meth:`gather`) of the same indices under the same RNG state are the same windows.
        """
        w = self.windows[index]
        n = min(w.stop - w.start, self.max_frames)
        u = self.unit_length
        if u > 1 and n >= 2 * u:
            n = (n // u - 1) * u if torch.randint(3, ()).item() == 0 else (n // u) * u
        n = max(n, 1)
        start = w.start + int(torch.randint(w.stop - w.start - n + 1, ()).item())
        caption = w.captions[int(torch.randint(len(w.captions), ()).item())] if w.captions else -1
        return n, start, caption

    def __getitem__(self, index: int) -> dict:
        n, start, k = self.draw(index)
        w = self.windows[index]
        x = self._shard(w.shard).features(w.clip, start, start + n)
        if self.normalize:
            x = (x - self.mean) / self.std
        return {"motion": torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)), "length": n,
                **self._labels(w, k)}

    def _labels(self, w: Window, caption: int) -> dict:
        c = self.captions[w.shard][w.clip][caption] if caption >= 0 else None
        return {"caption": c.text if c else "", "tokens": c.tokens if c else "",
                "action": int(self.actions[w.shard][w.clip]), "name": self.names[w.shard][w.clip]}

    def gather(self, indices: Sequence[int], table: FrameTable) -> dict:
        """``collate([self[i] for i in indices])`` from ``table``: the same draws, so bit for bit the same batch,
        with ``motion`` and ``mask`` on the table's device and no file read."""
        if table.key != self._table_key():
            raise ValueError("this frame table was made from other shards or another normalisation")
        draws = [self.draw(i) for i in indices]
        lengths = np.array([n for n, _, _ in draws])
        first = np.array([table.first_row(self.windows[i].shard, self.windows[i].clip) + start
                          for i, (_, start, _) in zip(indices, draws)])
        mask = np.arange(lengths.max())[None] < lengths[:, None]  # (B,L)
        rows = np.where(mask, first[:, None] + np.arange(mask.shape[1])[None], table.pad_row)
        labels = [self._labels(self.windows[i], k) for i, (_, _, k) in zip(indices, draws)]
        return {"motion": table.rows(rows), "length": torch.from_numpy(lengths),
                "mask": torch.from_numpy(mask).to(table.device),
                **{key: [b[key] for b in labels] for key in ("caption", "tokens")},
                "action": torch.tensor([b["action"] for b in labels]), "name": [b["name"] for b in labels]}

    def _table_key(self) -> tuple:
        return tuple(self.paths), self.normalize, self.mean.tobytes(), self.std.tobytes()

    def denormalize(self, x):
        """Undo the normalisation (numpy array or torch tensor)."""
        if isinstance(x, torch.Tensor):
            return x * torch.as_tensor(self.std, device=x.device) + torch.as_tensor(self.mean, device=x.device)
        return x * self.std + self.mean


class FrameTable:
    """Every frame of a dataset's shards in one (F+1, D) float32 tensor, normalised as the dataset draws them, the
    last row zeros (padding): a batch of windows is one gather (:meth:`MotionDataset.gather`), with no loader
    processes and no file read per step.

    Training on a GPU, the table lives in its memory when it takes at most a quarter of what is free (Bandai-Namco:
    0.5 GB; HumanML3D with mirrors: about 4 GB), else in pinned host memory; on the CPU, in host memory (each process
    of a torchrun run holds its own).
    """

    def __init__(self, ds: MotionDataset, device: torch.device | str = "cpu") -> None:
        self.key, self.device = ds._table_key(), torch.device(device)
        frames, self._offsets = [], []
        for path in ds.paths:
            with Shard(path) as shard:
                self._offsets.append(sum(len(x) for x in frames) + shard.offsets.astype(np.int64))
                frames.append(shard.all_features())
        rows, dim = sum(len(x) for x in frames) + 1, frames[0].shape[1]
        place = self.device
        if place.type == "cuda" and rows * dim * 4 > torch.cuda.mem_get_info(place)[0] / 4:
            place = torch.device("cpu")
        table = torch.zeros(rows, dim, dtype=torch.float32, pin_memory=place != self.device)
        at = 0
        for x in frames:
            for a in range(0, len(x), 1 << 16):  # normalised a slice at a time: the same float32 operations as an item's
                part = x[a : a + (1 << 16)]
                part = (part - ds.mean) / ds.std if ds.normalize else part
                table[at + a : at + a + len(part)] = torch.from_numpy(np.ascontiguousarray(part, dtype=np.float32))
            at += len(x)
        self.data, self.pad_row = table.to(place), rows - 1

    def first_row(self, shard: int, clip: int) -> int:
        """The table row of the clip's first frame."""
        return int(self._offsets[shard][clip])

    def rows(self, index: np.ndarray) -> torch.Tensor:
        """The table's rows at ``index`` (B,L) as a (B,L,D) tensor on the training device."""
        i = torch.from_numpy(index.reshape(-1))
        x = self.data.index_select(0, i.to(self.data.device)).view(*index.shape, self.data.shape[1])
        return x.pin_memory().to(self.device, non_blocking=True) if x.device != self.device else x


def collate(batch: list[dict]) -> dict:
    """Pad motions to the longest in the batch: ``motion`` (B,L,263), ``mask`` (B,L) True on real frames."""
    lengths = torch.tensor([b["length"] for b in batch])
    L = int(lengths.max())
    motion = torch.zeros(len(batch), L, batch[0]["motion"].shape[-1])
    for i, b in enumerate(batch):
        motion[i, : b["length"]] = b["motion"]
    return {
        "motion": motion,
        "length": lengths,
        "mask": torch.arange(L)[None] < lengths[:, None],
        "caption": [b["caption"] for b in batch],
        "tokens": [b["tokens"] for b in batch],
        "action": torch.tensor([b["action"] for b in batch]),
        "name": [b["name"] for b in batch],
    }


class LengthBucketSampler(Sampler[list[int]]):
    """Batches of similar lengths (less padding), in random order; shardable across processes.

    Indices are shuffled, cut into pools of ``pool_batches`` batches, sorted by length inside each pool
    and split into batches; the batches are shuffled again. ``num_replicas``/``rank`` give each
    process of a distributed run its own share of the batches.
    """

    def __init__(
        self,
        lengths: Sequence[int] | np.ndarray,
        batch_size: int,
        *,
        shuffle: bool = True,
        drop_last: bool = False,
        pool_batches: int = 50,
        seed: int = 0,
        num_replicas: int = 1,
        rank: int = 0,
    ) -> None:
        self.lengths = np.asarray(lengths)
        self.batch_size, self.shuffle, self.drop_last = batch_size, shuffle, drop_last
        self.pool_batches, self.seed = pool_batches, seed
        self.num_replicas, self.rank = num_replicas, rank
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _batches(self) -> list[list[int]]:
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(len(self.lengths)) if self.shuffle else np.arange(len(self.lengths))
        pool = self.batch_size * self.pool_batches
        batches: list[list[int]] = []
        for p in range(0, len(order), pool):
            chunk = order[p : p + pool]
            chunk = chunk[np.argsort(self.lengths[chunk], kind="stable")]
            batches += [chunk[b : b + self.batch_size].tolist() for b in range(0, len(chunk), self.batch_size)]
        if self.drop_last:
            batches = [b for b in batches if len(b) == self.batch_size]
        if self.shuffle:
            batches = [batches[i] for i in rng.permutation(len(batches))]
        usable = len(batches) - len(batches) % self.num_replicas if self.num_replicas > 1 else len(batches)
        return batches[self.rank : usable : self.num_replicas]

    def __iter__(self) -> Iterator[list[int]]:
        return iter(self._batches())

    def __len__(self) -> int:
        return len(self._batches())
