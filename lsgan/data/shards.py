"""HDF5 motion shards: the one file format between ``lsgan preprocess`` and everything downstream.

Layout (format ``lsgan-motion-shard``, version 2; every string is UTF-8)::

    /features            (F, 263) float32   all clips' frames, concatenated; chunked, gzip + shuffle
    /clips/name          (N,) str           unique clip id ('M' + id for a mirrored copy)
    /clips/offset        (N,) int64         first row of the clip in /features
    /clips/length        (N,) int32         frames of the clip
    /clips/split         (N,) str           'train' | 'val' | 'test'
    /clips/action        (N,) int32         index into the root attribute action_names, -1 = none
    /clips/source_file   (N,) str           input file the clip came from
    /clips/mirror_of     (N,) str           id of the clip this one mirrors, '' if none
    /captions/clip       (M,) int32         the clip each caption describes
    /captions/text       (M,) str
    /captions/tokens     (M,) str           word/POS tokens: the dataset's own (HumanML3D's spaCy tags), else
                                            tagged at import by lsgan.data.tokens
    /captions/start      (M,) float64       time tags in seconds, each ``float()`` of its text (NaN kept);
    /captions/end        (M,) float64       lsgan.data.captions.span_frames turns them into frames (T2M's rule)
    /stats/mean, /stats/std  (263,) float32 normalisation statistics (attribute 'origin' says whose)
    /provenance          () str             JSON: inputs with sha256, options, source, versions

Root attributes: format, format_version, lsgan_version, source, fps (20), feature_dim (263),
num_joints (22), action_names (JSON list).

Version 1 (still read) stored the tags as float32 and could leave tokens empty. Reading one, each tag
becomes ``float`` of its shortest float32 decimal (the text, for any tag of up to 7 significant digits, so
the frames are T2M's again) and empty tokens are tagged with lsgan.data.tokens, as an import now does.
Version 1 files made from HumanML3D counted a caption with one NaN tag as whole-clip; T2M does not (see
span_frames): preprocess again to get those spans.

A file that cannot be read or written raises :class:`DataFileError` (a ValueError), one line that
starts with the file's path. Every HDF5 file lsgan reads is opened by :func:`open_hdf5`, which refuses data
from outside the file (external storage, external links, virtual datasets) and datasets declaring more than
the file can hold (or, chunked, more than the chunks it stores can inflate to); a shard's clip table is checked
against its features when it is opened. Strings are read by :class:`StringReader`, against a budget tied to the
file's size, and numeric columns by :func:`numbers`, which refuses any other type before reading it.
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from lsgan import __version__
from lsgan.data.clip import Caption
from lsgan.data.skeleton import FEATURE_DIM, FPS, NUM_JOINTS
from lsgan.data.tokens import tokenize
from lsgan.io import atomic_path, discard, publish
from lsgan.pickles import DEFLATE_MAX_RATIO

FORMAT = "lsgan-motion-shard"
FORMAT_VERSION = 2
_STR = h5py.string_dtype("utf-8")
_CHUNK_ROWS = 1024
_SHARD = "an lsgan motion shard"
_DATASETS = ("features", "clips/name", "clips/offset", "clips/length", "clips/split", "clips/action",
             "clips/source_file", "clips/mirror_of", "captions/clip", "captions/text", "captions/tokens",
             "captions/start", "captions/end", "stats/mean", "stats/std")
_ATTRS = ("format_version", "source", "fps", "action_names")
_CLIP_COLUMNS = ("offset", "length", "split", "action", "source_file", "mirror_of")
_CAPTION_COLUMNS = ("text", "tokens", "start", "end")

MAX_COMPRESSED_BYTES = 64 << 30
"""Most bytes (64 GiB) a compressed (chunked and filtered) dataset may declare: such a dataset may rightly hold
more than the file's size, so the file cannot bound it. About 10x the largest dataset lsgan imports: all of
AMASS (some 40 hours, 2.9 M frames at 20 fps), mirrored, is 5.8 M frames of 263 float32, about 6 GB of
features. Any other dataset may declare at most the file's size."""

CONTENT_MAX_RATIO = 64
"""The most a compressed dataset of a shard or latent cache may declare over what it stores: lsgan's own files
compress 1.2-2x (motion features at gzip level 1 with shuffle: 1.57x on synthetic clips, less on mocap, whose
noise does not compress); 64x leaves room for long still takes and refuses chunks of zeros that deflate would
inflate 1032x (a 6 MB file asking for 6 GB of memory)."""

FEATURE_LIMIT = 1e4
"""The largest magnitude a shard's feature may have: positions and velocities in metres (per frame), rotations and
contacts within [-1, 1]; no human motion comes near, and float16 training would overflow far above it."""
UNUSABLE = f"NaN, infinite or values beyond ±{FEATURE_LIMIT:g}"


def unusable_rows(x: np.ndarray) -> np.ndarray:
    """The rows of features (T, 263) holding a value that is not finite or beyond :data:`FEATURE_LIMIT`."""
    return np.flatnonzero(~(np.abs(x) <= FEATURE_LIMIT).all(axis=1))  # NaN compares false


CONTENT_FLOOR = 256 << 20
"""Up to this many declared bytes (about 3.5 hours of motion) a compressed dataset may inflate as far as its filters
can: a quarter of a GiB puts no machine at risk, and a file damaged into constant values (its features overwritten
with NaN) reaches the check that says so; above it, such a file reads as what it resembles, a decompression bomb."""

FILTER_MAX_RATIO = {h5py.h5z.FILTER_DEFLATE: DEFLATE_MAX_RATIO, h5py.h5z.FILTER_LZF: 88, h5py.h5z.FILTER_SHUFFLE: 1,
                    h5py.h5z.FILTER_FLETCHER32: 1}
"""The most each HDF5 filter can shrink data: deflate (gzip) 1032x, its format's limit; LZF 88x (a back reference
copies at most 264 bytes and takes 3); shuffle and the checksum nothing. A chunked dataset may declare at most its
stored bytes times the ratios of its filters: more would be data that no stored byte holds. A filter not listed
(szip, scale-offset, n-bit, plugins; lsgan writes gzip only) counts as 1x, as uncompressed data does."""

STRING_BUDGET_FACTOR, STRING_BUDGET_SLACK = 4, 16 << 20
"""The strings of one file may decode to at most 4x its size plus 16 MiB (counted with STRING_ITEM_BYTES each).
HDF5 stores each variable-length string whole and uncompressed (a 16-byte reference in the dataset, the text and
a 16-byte header in a global heap), so the strings of a file lsgan wrote count less than 2x its size; references
that share one stored string are how a 33 MB file decodes to terabytes."""

STRING_ITEM_BYTES = 50
"""What one decoded string costs besides its text (CPython's str header is 49 bytes), so that a billion empty
strings count too."""

STRING_BLOCK = 64
"""Most strings read at once (h5py's per-read overhead, about 35 us, is paid once per block)."""


class DataFileError(ValueError):
    """A data file that cannot be read or written; the message is one line starting with the file's path.

    A DataLoader worker's error is raised again in the main process with the worker's traceback as its
    message; only the original line is kept.
    """

    def __init__(self, message: str = "") -> None:
        marker = f"{type(self).__module__}.{type(self).__qualname__}: "
        if message.startswith("Caught ") and marker in message:
            message = message[message.rindex(marker) + len(marker):].strip()
        super().__init__(re.sub(r"\s*\n\s*", " ", message))  # one line, whatever a name read from the file holds


def _reason(e: BaseException) -> str:
    """h5py's message without its 'Unable to ... (' wrapper, on one line."""
    text = str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)
    m = re.fullmatch(r"(?:Unable to|Can't) [^(]*\((.*)\)", text, re.S)
    return " ".join((m.group(1) if m else text).split())


def open_hdf5(path: str | os.PathLike) -> h5py.File:
    """Open an HDF5 file to read, or raise DataFileError saying plainly why it cannot be (including data from
    outside the file and datasets larger than it can hold: see :func:`check_storage`)."""
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise DataFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DataFileError(f"{path}: is a directory, not an HDF5 file") from None
    except PermissionError:
        raise DataFileError(f"{path}: cannot read (permission denied)") from None
    except OSError as e:
        reason = _reason(e)
        if "file signature not found" in reason:
            raise DataFileError(f"{path}: not an HDF5 file") from None
        raise DataFileError(f"{path}: truncated or corrupt HDF5 ({reason})") from None
    try:
        with reading(path, "an HDF5 file lsgan reads"):
            check_storage(f, path)
    except BaseException:
        f.close()
        raise
    return f


def check_storage(f: h5py.File, path: str | os.PathLike) -> None:
    """Refuse (DataFileError) external links, and datasets with external storage, virtual datasets or a declared
    size beyond what the file can hold (:func:`_check_dataset`): HDF5 would read other files on the machine, or
    fill gigabytes with nothing, when asked for them."""
    size = os.path.getsize(path)
    objects: list[str] = []
    external: list[tuple[str, h5py.ExternalLink]] = []

    def look(name: str, link) -> bool | None:  # raising in here is lost in h5py's C callback: stop, then raise
        if isinstance(link, h5py.ExternalLink):
            external.append((name, link))
            return True
        if isinstance(link, h5py.HardLink):
            objects.append(name)
        return None

    f.visititems_links(look)
    if external:
        name, link = external[0]
        raise DataFileError(f"{path}: refused: {name} is an external link to {link.filename}:{link.path} "
                            "(lsgan reads only what is inside the file)")
    for name in ["/", *objects]:
        obj = f[name]
        _check_attributes(obj, name, path, size)
        if isinstance(obj, h5py.Dataset):
            _check_dataset(obj, name, path, size)


def _declared_bytes(shape: tuple[int, ...] | None, type_id) -> int:
    """Bytes a dataset or attribute of ``shape`` (None: empty) and HDF5 type claims (variable-length: 16 each)."""
    return 0 if shape is None else int(np.prod(shape, dtype=object)) * type_id.get_size()


def _check_attributes(obj, name: str, path: str | os.PathLike, file_size: int) -> None:
    """Attributes are read whole: none may declare more bytes than the file holds, and variable-length data only
    as one string (lsgan writes no other; an array of references to one large stored string decodes to it again
    for every entry)."""
    for key in obj.attrs:
        attr = obj.attrs.get_id(key)
        declared = _declared_bytes(attr.shape, attr.get_type())
        if declared > file_size:
            raise DataFileError(f"{path}: refused: attribute {key} of {name} declares {declared:,} bytes, more than "
                                f"the file's {file_size:,}")
        if attr.dtype.hasobject and not (attr.shape == () and h5py.check_string_dtype(attr.dtype)):
            raise DataFileError(f"{path}: refused: attribute {key} of {name} holds variable-length data of shape "
                                f"{attr.shape}, not one string")


def _check_dataset(ds: h5py.Dataset, name: str, path: str | os.PathLike, file_size: int) -> None:
    """Data from the file only, and no more than it can hold: the file's size, or MAX_COMPRESSED_BYTES when
    compressed (a compressed dataset may rightly hold more than the file)."""
    if ds.is_virtual:
        raise DataFileError(f"{path}: refused: dataset {name} is virtual (it maps data from other files)")
    if ds.external:
        files = ", ".join(sorted({str(e[0]) for e in ds.external}))
        raise DataFileError(f"{path}: refused: dataset {name} keeps its data in other files ({files})")
    declared = _declared_bytes(ds.shape, ds.id.get_type())
    filtered = ds.id.get_create_plist().get_nfilters() > 0
    limit = MAX_COMPRESSED_BYTES if filtered else file_size
    if declared > limit:
        what = f"the {MAX_COMPRESSED_BYTES:,}-byte limit of compressed data" if filtered else \
            f"the file's {file_size:,} bytes"
        raise DataFileError(f"{path}: refused: dataset {name} declares {ds.shape} items, {declared:,} bytes, more "
                            f"than {what}")
    if ds.chunks is not None:
        problem = _chunks_problem(ds, declared)
        if problem is not None:
            raise DataFileError(f"{path}: refused: dataset {name} declares {ds.shape} items, {declared:,} bytes, "
                                f"but {problem}")


def _chunks_problem(ds: h5py.Dataset, declared: int) -> str | None:
    """What a chunked dataset lacks to hold what it declares, in words; None if nothing. A file lsgan writes stores
    every chunk (an unwritten one reads as zeros: a few chunks of a resizable dataset could declare 31 GiB), and no
    filter inflates past :data:`FILTER_MAX_RATIO` of what is stored."""
    needed = math.prod(-(-n // c) for n, c in zip(ds.shape, ds.chunks))
    stored = ds.id.get_num_chunks()
    if stored < needed:
        return f"stores only {stored:,} of its {needed:,} chunks (unwritten chunks would read as zeros)"
    plist = ds.id.get_create_plist()
    filters = [plist.get_filter(i) for i in range(plist.get_nfilters())]  # (code, flags, options, name)
    stored_bytes = ds.id.get_storage_size()
    ratio = math.prod(FILTER_MAX_RATIO.get(f[0], 1) for f in filters) if filters else 1
    ratio = ratio if declared <= CONTENT_FLOOR else min(ratio, CONTENT_MAX_RATIO)
    capacity = stored_bytes * ratio
    if declared > capacity:
        names = ", ".join(f[3].decode("ascii", "replace") or str(f[0]) for f in filters) or "none"
        return f"its {stored_bytes:,} stored bytes inflate to at most {capacity:,} (filters: {names})"
    return None


@contextmanager
def reading(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Turn what h5py or a malformed file raises while ``path`` is read into a DataFileError.

    ``what`` names the expected content, e.g. 'an lsgan motion shard'.
    """
    try:
        yield
    except DataFileError:
        raise
    except (OSError, RuntimeError) as e:
        raise DataFileError(f"{path}: truncated or corrupt HDF5 ({_reason(e)})") from None
    except (KeyError, ValueError, TypeError, IndexError, AttributeError) as e:
        raise DataFileError(f"{path}: not {what} ({_reason(e)})") from None


def check_layout(f: h5py.File, path: str | os.PathLike, what: str, fmt: str, version: int,
                 datasets: Iterable[str], attrs: Iterable[str], hint: str = "") -> None:
    """Refuse (DataFileError) a file whose format attribute, version, datasets or attributes are not ``what``'s.

    ``hint`` follows the reason when the format attribute is not ``fmt`` (e.g. which command makes one).
    """
    found = f.attrs.get("format")
    if found != fmt:
        said = "no format attribute" if found is None else f"format attribute is {found!r}"
        raise DataFileError(f"{path}: not {what} ({said}{'; ' + hint if hint else ''})")
    missing = [k for k in datasets if k not in f] + [f"attribute {a}" for a in attrs if a not in f.attrs]
    if missing:
        more = f" and {len(missing) - 4} more" if len(missing) > 5 else ""
        raise DataFileError(f"{path}: not {what} (missing {', '.join(missing[:4] if more else missing)}{more})")
    if int(f.attrs["format_version"]) > version:
        raise DataFileError(f"{path}: format version {f.attrs['format_version']} is newer than this lsgan reads "
                            f"({version})")


def check_writable(path: str | os.PathLike) -> None:
    """Refuse (DataFileError) an output path that is a directory or lies where no file can be made."""
    path = Path(path)
    with writing(path):
        if path.is_dir():
            raise DataFileError(f"{path}: cannot write (is a directory)")
        folder = next(p for p in path.parents if p.exists())
        if not folder.is_dir():
            raise DataFileError(f"{path}: cannot write ({folder} is a file, not a folder)")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise DataFileError(f"{path}: cannot write (permission denied)")


def check_space(path: Path, need_bytes: int) -> None:
    """Refuse (DataFileError) writing ``need_bytes`` beside ``path`` when the disk has less free space."""
    folder = next(p for p in [path.parent, *path.parents] if p.exists())
    free = shutil.disk_usage(folder).free
    if need_bytes > free:
        raise DataFileError(f"{path}: disk full: writing it needs up to {need_bytes / 1e6:,.1f} MB and "
                            f"{folder.resolve()} has {free / 1e6:,.1f} MB free")


@contextmanager
def writing(path: str | os.PathLike) -> Iterator[None]:
    """Turn an OSError of creating, or renaming into, ``path`` into a DataFileError naming it."""
    try:
        yield
    except IsADirectoryError:
        raise DataFileError(f"{path}: cannot write (is a directory)") from None
    except PermissionError:
        raise DataFileError(f"{path}: cannot write (permission denied)") from None
    except OSError as e:
        raise DataFileError(f"{path}: cannot write ({(e.strerror or _reason(e)).lower()})") from None


@dataclass
class ClipRecord:
    """A featurised clip, ready to be stored."""

    name: str
    features: np.ndarray  # (T, 263) float32
    split: str
    source_file: str = ""
    captions: list[Caption] = field(default_factory=list)
    action: str | None = None
    mirror_of: str | None = None


class _Accumulator:
    """Streaming per-feature mean and std (float64 sums) over the frames it is given."""

    def __init__(self) -> None:
        self.n = 0
        self.s = np.zeros(FEATURE_DIM)
        self.ss = np.zeros(FEATURE_DIM)

    def add(self, x: np.ndarray) -> None:
        x = x.astype(np.float64)
        self.n += len(x)
        self.s += x.sum(0)
        self.ss += (x * x).sum(0)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        from lsgan.data.features import group_std

        if self.n == 0:
            return np.zeros(FEATURE_DIM, np.float32), np.ones(FEATURE_DIM, np.float32)
        mean = self.s / self.n
        std = np.sqrt(np.maximum(self.ss / self.n - mean * mean, 0.0))
        return mean.astype(np.float32), group_std(std)


def _write_tables(f: h5py.File, cols: dict[str, list], caps: dict[str, list], stats: tuple | None,
                  acc: _Accumulator | None, *, source: str, action_names: list[str], provenance: dict) -> None:
    """The clip and caption tables, the statistics, the provenance and the root attributes of a shard."""
    g = f.create_group("clips")
    for key in ("name", "split", "source_file", "mirror_of"):
        g.create_dataset(key, data=np.array(cols[key], dtype=object), dtype=_STR, track_times=False)
    g.create_dataset("offset", data=np.array(cols["offset"], dtype=np.int64), track_times=False)
    g.create_dataset("length", data=np.array(cols["length"], dtype=np.int32), track_times=False)
    g.create_dataset("action", data=np.array(cols["action"], dtype=np.int32), track_times=False)
    g = f.create_group("captions")
    g.create_dataset("clip", data=np.array(caps["clip"], dtype=np.int32), track_times=False)
    for key in ("text", "tokens"):
        g.create_dataset(key, data=np.array(caps[key], dtype=object), dtype=_STR, track_times=False)
    for key in ("start", "end"):
        g.create_dataset(key, data=np.array(caps[key], dtype=np.float64), track_times=False)

    mean, std = stats if stats is not None else acc.result()
    g = f.create_group("stats")
    g.create_dataset("mean", data=np.asarray(mean, np.float32), track_times=False)
    g.create_dataset("std", data=np.asarray(std, np.float32), track_times=False)
    g.attrs["origin"] = "source" if stats is not None else "train split (HumanML3D group rule)"
    f.create_dataset("provenance", data=json.dumps(provenance, sort_keys=True), dtype=_STR, track_times=False)
    f.attrs.update(
        format=FORMAT, format_version=FORMAT_VERSION, lsgan_version=__version__, source=source,
        fps=FPS, feature_dim=FEATURE_DIM, num_joints=NUM_JOINTS, action_names=json.dumps(action_names),
    )


@contextmanager
def hdf5_output(path: str | os.PathLike, need_bytes: int = 0, **options) -> Iterator[h5py.File]:
    """An HDF5 file (h5py ``options``) open for writing beside ``path``; it replaces ``path`` when the block ends
    without error, and on any error (or Ctrl-C) it is removed and ``path`` is left as it was. Failing to create or
    rename it raises a DataFileError naming ``path``.

    ``need_bytes``: what the file will take at most; less free space is refused before HDF5 starts, because
    h5py crashes the process (SIGSEGV in its own error path) when the disk fills during a write."""
    path = Path(path)
    check_writable(path)
    check_space(path, need_bytes)
    with writing(path):
        fd, tmp = atomic_path(path)
    os.close(fd)
    try:
        with h5py.File(tmp, "w", **options) as f:
            yield f
        with writing(path):
            publish(tmp, path)
    except BaseException:
        discard(tmp)
        raise


class _ShardWriter:
    """The clips of a shard as they stream in: features appended in blocks of chunks, the clip and caption columns
    and the train split's statistics gathered for the tables written at the end."""

    def __init__(self, f: h5py.File, action_names: list[str], compute_stats: bool) -> None:
        self.feats = f.create_dataset(
            "features", shape=(0, FEATURE_DIM), maxshape=(None, FEATURE_DIM), dtype=np.float32,
            chunks=(_CHUNK_ROWS, FEATURE_DIM), compression="gzip", compression_opts=1, shuffle=True,
            track_times=False,
        )
        self.action_index = {a: i for i, a in enumerate(action_names)}
        self.acc = _Accumulator() if compute_stats else None
        self.cols: dict[str, list] = {k: [] for k in ("name", "offset", "length", "split", "action", "source_file",
                                                      "mirror_of")}
        self.caps: dict[str, list] = {k: [] for k in ("clip", "text", "tokens", "start", "end")}
        self.rows = 0
        self.buffer: list[np.ndarray] = []
        self.buffered = 0

    def add(self, clip: ClipRecord) -> None:
        x = np.asarray(clip.features, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != FEATURE_DIM:
            raise ValueError(f"clip {clip.name}: features of shape {x.shape}, expected (T, {FEATURE_DIM})")
        if len(bad := unusable_rows(x)):  # a shard lsgan writes is one it reads
            raise ValueError(f"clip {clip.name}: frame {bad[0]}: features hold {UNUSABLE}")
        i, cols = len(self.cols["name"]), self.cols
        for key, value in (("name", clip.name), ("offset", self.rows), ("length", len(x)), ("split", clip.split),
                           ("action", self.action_index[clip.action] if clip.action is not None else -1),
                           ("source_file", clip.source_file), ("mirror_of", clip.mirror_of or "")):
            cols[key].append(value)
        for c in clip.captions:
            for key, value in (("clip", i), ("text", c.text), ("tokens", c.tokens), ("start", c.start),
                               ("end", c.end)):
                self.caps[key].append(value)
        if clip.split == "train" and self.acc is not None:
            self.acc.add(x)
        self.rows += len(x)
        self.buffer.append(x)
        self.buffered += len(x)
        if self.buffered >= 16 * _CHUNK_ROWS:
            self.flush()

    def flush(self) -> None:
        if self.buffer:
            block = np.concatenate(self.buffer)
            self.feats.resize(self.feats.shape[0] + len(block), axis=0)
            self.feats[-len(block):] = block
            self.buffer.clear()
            self.buffered = 0


def write_shard(
    path: str | os.PathLike,
    clips: Iterable[ClipRecord],
    *,
    source: str,
    action_names: list[str],
    provenance: dict,
    stats: tuple[np.ndarray, np.ndarray] | None = None,
    need_bytes: int = 0,
) -> dict:
    """Write clips (streamed, in order) to an HDF5 shard atomically; returns a summary. ``need_bytes``: an upper
    bound of its size, checked against the free space first (see :func:`hdf5_output`).

    ``stats`` keeps given Mean/Std (a processed HumanML3D folder's own); otherwise they are computed
    on the train split with HumanML3D's rule (per-feature mean; std averaged within each group).
    """
    with hdf5_output(path, need_bytes, track_order=True) as f:
        w = _ShardWriter(f, action_names, compute_stats=stats is None)
        for clip in clips:
            w.add(clip)
        w.flush()
        _write_tables(f, w.cols, w.caps, stats, w.acc, source=source, action_names=action_names,
                      provenance=provenance)
    return {"clips": len(w.cols["name"]), "frames": w.rows, "captions": len(w.caps["text"])}


def numbers(ds: h5py.Dataset) -> np.ndarray:
    """A numeric dataset, read whole; any other type (strings, variable-length or compound data, which could decode
    to far more than the file holds) is refused by name before anything is read."""
    if ds.dtype.kind not in "biuf":
        raise ValueError(f"{ds.name.lstrip('/')} holds {ds.dtype}, not numbers")
    return ds[()]


def _decoded(values) -> list[str]:
    return [v.decode("utf-8") if isinstance(v, bytes) else v for v in values]


def _stored_lengths(ds: h5py.Dataset, path: str | os.PathLike, address_size: int) -> np.ndarray | None:
    """The byte length of every string of a contiguous variable-length string dataset, from the references it
    stores (a 4-byte little-endian length, a global heap address, a 4-byte index), without decoding any; None when
    its strings are stored otherwise (chunked, compact, not yet written)."""
    if ds.id.get_create_plist().get_layout() != h5py.h5d.CONTIGUOUS or ds.id.get_offset() is None:
        return None
    width = 4 + address_size + 4
    with open(path, "rb") as fh:  # no more than the file holds: check_storage bounds a contiguous dataset by it
        fh.seek(ds.id.get_offset())
        raw = fh.read(ds.size * width)
    if len(raw) != ds.size * width:
        return None
    return np.frombuffer(raw, np.dtype([("length", "<u4"), ("heap", f"V{width - 4}")]))["length"].astype(np.int64)


class StringReader:
    """The string datasets and attributes of one open file, read against one budget: together they may decode to at
    most STRING_BUDGET_FACTOR x the file's size + STRING_BUDGET_SLACK, else DataFileError naming the file.

    Contiguous variable-length strings (lsgan's layout) and fixed-length ones are costed exactly before they are
    read. Other layouts (chunked or compact: not lsgan's) are read in blocks sized so that their worst case, every
    entry a copy of one stored string as large as the file (held twice: HDF5's buffer and Python's copy), fits in
    what is left: STRING_BLOCK entries for small files, down to one for large ones (slower, never larger).
    Attributes are read one at a time, each at most one stored string (see :func:`check_storage`). Worst case: the
    budget plus twice the file's size.
    """

    def __init__(self, f: h5py.File, path: str | os.PathLike) -> None:
        self.f, self.path = f, path
        self.size = os.path.getsize(path)
        self.limit = STRING_BUDGET_FACTOR * self.size + STRING_BUDGET_SLACK
        self.used = 0

    def __call__(self, name: str) -> list[str]:
        """The strings of dataset ``name`` (1-d; a scalar gives one) as str."""
        ds = self.f[name]
        if h5py.check_string_dtype(ds.dtype) is None or ds.ndim > 1:
            raise ValueError(f"{name} holds {ds.dtype} of shape {ds.shape}, not a list of strings")
        cost = self._known_cost(ds)
        if cost is None:
            return self._blocks(ds, name)
        self._spend(cost, f"{name}: {ds.size:,} strings, {cost:,} bytes")
        return _decoded([ds[()]] if ds.ndim == 0 else ds[()])

    def attributes(self, obj) -> dict:
        """The attributes of ``obj``, counted as they are read."""
        out = {}
        for key in obj.attrs:
            out[key] = value = obj.attrs[key]
            size = value.nbytes if isinstance(value, np.ndarray) else len(value) if isinstance(value, str | bytes) \
                else 0
            self._spend(size + STRING_ITEM_BYTES, f"reached with attribute {key}")
        return out

    def _known_cost(self, ds: h5py.Dataset) -> int | None:
        """What the strings of ``ds`` take decoded, when that can be told without decoding them."""
        length = h5py.check_string_dtype(ds.dtype).length
        if length is not None:
            return ds.size * (length + STRING_ITEM_BYTES)
        stored = _stored_lengths(ds, self.path, self.f.id.get_create_plist().get_sizes()[0])
        return None if stored is None else int(stored.sum()) + ds.size * STRING_ITEM_BYTES

    def _blocks(self, ds: h5py.Dataset, name: str) -> list[str]:
        """The strings of a dataset whose cost is not known beforehand, counted block by block."""
        if ds.ndim == 0:
            value = ds[()]
            self._spend(len(value) + STRING_ITEM_BYTES, f"reached in {name}")
            return _decoded([value])
        out: list[str] = []
        while len(out) < ds.size:
            room = (self.limit - self.used) // (2 * max(self.size, 1))
            block = ds[len(out) : len(out) + max(1, min(STRING_BLOCK, room))]
            self._spend(sum(len(v) for v in block) + len(block) * STRING_ITEM_BYTES, f"reached in {name}")
            out += _decoded(block)
        return out

    def _spend(self, cost: int, what: str) -> None:
        self.used += cost
        if self.used > self.limit:
            raise DataFileError(f"{self.path}: refused: its strings would decode to more than {self.limit:,} bytes "
                                f"({STRING_BUDGET_FACTOR}x the file's {self.size:,} + {STRING_BUDGET_SLACK >> 20} MiB; "
                                f"{what}): entries that share one stored string?")


def _read_captions(f: h5py.File, strings: StringReader, clips: int, version: int) -> list[list[Caption]]:
    """Each clip's captions; a version 1 file's float32 tags and empty tokens are brought to version 2's."""
    texts, tokens = strings("captions/text"), strings("captions/tokens")
    starts, ends = numbers(f["captions/start"]), numbers(f["captions/end"])
    if version < 2:
        starts, ends = ([float(str(np.float32(t))) for t in tags] for tags in (starts, ends))
        tokens = [tok or tokenize(text) for text, tok in zip(texts, tokens)]
    captions: list[list[Caption]] = [[] for _ in range(clips)]
    for i, c in enumerate(numbers(f["captions/clip"])):
        captions[c].append(Caption(texts[i], tokens[i], float(starts[i]), float(ends[i])))
    return captions


def _table_problem(f: h5py.File, names: list[str], offsets: np.ndarray, lengths: np.ndarray, actions: np.ndarray,
                   num_actions: int) -> str | None:
    """What is wrong with a shard's clip columns against its features, in words naming the clip; None if nothing."""
    n = len(names)
    for col in _CLIP_COLUMNS:
        if f[f"clips/{col}"].shape != (n,):
            return f"clips/{col} has shape {f[f'clips/{col}'].shape}, clips/name ({n},): a damaged clip table"
    if any(a.dtype.kind not in "iu" for a in (offsets, lengths, actions)):
        return "clips/offset, clips/length and clips/action must hold integers"
    rows = f["features"].shape[0] if f["features"].ndim == 2 else 0
    ends = offsets.astype(np.int64) + lengths
    checks = ((offsets < 0, "offset {o} is negative"), (lengths < 1, "length {k} is not a positive frame count"),
              (ends > rows, "frames {o}-{e} lie outside the {rows} rows of features"),
              ((actions < -1) | (actions >= num_actions), "action {a} is not an index into the {na} action names"))
    for bad, text in checks:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            o, k = int(offsets[i]), int(lengths[i])
            return f"clip {names[i]} (index {i}): " + text.format(o=o, k=k, e=o + k, rows=rows, a=int(actions[i]),
                                                                   na=num_actions)
    end = int(ends.max()) if n else 0
    if rows > end:  # a shard holds its clips' frames and nothing else
        return f"features declares {rows:,} rows but its clips use {end:,}"
    return None


def _widths_problem(f: h5py.File) -> str | None:
    """The features must be numbers, and they and the statistics FEATURE_DIM wide."""
    want = {"features": (None, FEATURE_DIM), "stats/mean": (FEATURE_DIM,), "stats/std": (FEATURE_DIM,)}
    if f["features"].dtype.kind not in "biuf":
        return f"features holds {f['features'].dtype}, the format says float32"
    for name, shape in want.items():
        got = f[name].shape
        if got is None or len(got) != len(shape) or any(w is not None and g != w for g, w in zip(got, shape)):
            form = f"(frames, {FEATURE_DIM})" if name == "features" else f"({FEATURE_DIM},)"
            return f"{name} has shape {got}, the format says {form}"
    return None


def _captions_problem(f: h5py.File, clips: int) -> str | None:
    """Caption columns of one length whose clip indices exist."""
    m = f["captions/clip"].shape
    for col in _CAPTION_COLUMNS:
        if f[f"captions/{col}"].shape != m:
            return f"captions/{col} has shape {f[f'captions/{col}'].shape}, captions/clip {m}: a damaged caption table"
    clip = numbers(f["captions/clip"])
    if clip.dtype.kind not in "iu" or (len(clip) and (clip.min() < 0 or clip.max() >= clips)):
        return f"captions/clip holds indices outside the {clips} clips"
    return None


class Shard:
    """Read access to one shard. The clip table is loaded at once; features are read on demand.

    A file that is not a readable shard, or a clip whose frames cannot be read, raises DataFileError.

    >>> with Shard("bandai.h5") as shard:
    ...     x = shard.features(0)          # (T, 263) float32
    """

    def __init__(self, path: str | os.PathLike, in_memory: bool = False) -> None:
        self.path = Path(path)
        self._file = open_hdf5(self.path)
        try:
            with reading(self.path, _SHARD):
                self._load(self._file, in_memory)
        except BaseException:
            self._file.close()
            raise

    def _load(self, f: h5py.File, in_memory: bool) -> None:
        """The clip table, captions and statistics; the features too when ``in_memory``."""
        check_layout(f, self.path, _SHARD, FORMAT, FORMAT_VERSION, _DATASETS, _ATTRS)
        self.source: str = f.attrs["source"]
        self.fps = int(f.attrs["fps"])
        self.action_names: list[str] = json.loads(f.attrs["action_names"])
        strings = StringReader(f, self.path)
        self.names = strings("clips/name")
        self.offsets = numbers(f["clips/offset"])
        self.lengths = numbers(f["clips/length"])
        self.splits = np.array(strings("clips/split"))
        self.actions = numbers(f["clips/action"])
        self.source_files = strings("clips/source_file")
        self.mirror_of = strings("clips/mirror_of")
        self.mean = numbers(f["stats/mean"])
        self.std = numbers(f["stats/std"])
        bad = int(np.sum(~(np.isfinite(self.std) & (self.std > 0)) | ~np.isfinite(self.mean)))
        if bad:
            raise DataFileError(f"{self.path}: stats/mean and stats/std hold {bad} value{'s' * (bad != 1)} that cannot "
                                "normalise features (a std of zero or below, or a value not finite)")
        self.stats_origin = f["stats"].attrs.get("origin", "")
        self._check_table(f)
        self._captions = _read_captions(f, strings, len(self.names), int(f.attrs["format_version"]))
        self.attrs = strings.attributes(f)
        self._features = f["features"]
        self._compressed = self._features.compression is not None
        if in_memory:
            self._features = self.all_features()

    def _check_table(self, f: h5py.File) -> None:
        """Refuse (DataFileError) a clip table that does not fit the format: columns of one length, every clip's
        frames inside /features, widths of 263, actions and caption clips that exist."""
        problem = (_widths_problem(f)
                   or _table_problem(f, self.names, self.offsets, self.lengths, self.actions, len(self.action_names))
                   or _captions_problem(f, len(self.names)))
        if problem is not None:
            raise DataFileError(f"{self.path}: {problem}")

    def all_features(self) -> np.ndarray:
        """Every clip's frames, concatenated as stored: (num_frames, 263) float32, read at once (or the copy an
        ``in_memory`` shard holds); a damaged chunk is reported with the first clip whose frames it holds."""
        if isinstance(self._features, np.ndarray):
            return self._features
        try:
            x = self._features[()]
        except (OSError, RuntimeError):
            for i in range(len(self)):
                self.features(i)
            raise
        return self._finite(x, 0)

    def _finite(self, x: np.ndarray, row: int) -> np.ndarray:
        """``x``, the feature rows from ``row`` on, if every value is usable (:func:`unusable_rows`; lsgan writes none
        that is not), else a DataFileError naming the first clip and frame that holds one. A slice at a time."""
        for a in range(0, len(x), 1 << 16):
            rows = unusable_rows(x[a : a + (1 << 16)])
            if len(rows):
                bad = row + a + int(rows[0])
                i = int(np.searchsorted(self.offsets, bad, side="right")) - 1
                i = i if 0 <= i < len(self) and self.offsets[i] + self.lengths[i] > bad else None
                where = f"clip {self.names[i]} (index {i}), frame {bad - int(self.offsets[i])}" if i is not None \
                    else f"row {bad}"
                raise DataFileError(f"{self.path}: {where}: features hold {UNUSABLE} (lsgan writes none; the file "
                                    "was changed after it was written)")
        return x

    @property
    def provenance(self) -> dict:
        with reading(self.path, _SHARD):
            return json.loads(StringReader(self._file, self.path)("provenance")[0])

    def __len__(self) -> int:
        return len(self.names)

    @property
    def num_frames(self) -> int:
        return int(self.lengths.sum())

    def features(self, i: int, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Frames [start, stop) of clip i, (T, 263) float32."""
        n = int(self.lengths[i])
        stop = n if stop is None else min(stop, n)
        o = int(self.offsets[i])
        try:
            x = self._features[o + start : o + stop]
        except (OSError, RuntimeError) as e:
            damage = f"corrupt compressed data: {_reason(e)}" if self._compressed else _reason(e)
            raise DataFileError(f"{self.path}: clip {self.names[i]} (index {i}): unreadable features ({damage})") from None
        return self._finite(np.asarray(x, dtype=np.float32), o + start)

    def captions(self, i: int) -> list[Caption]:
        return list(self._captions[i])

    def action(self, i: int) -> str | None:
        a = int(self.actions[i])
        return self.action_names[a] if a >= 0 else None

    def indices(self, split: str | None = None) -> np.ndarray:
        """Indices of the clips of a split (all when None)."""
        return np.arange(len(self)) if split is None else np.flatnonzero(self.splits == split)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> Shard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def summarize(path: str | os.PathLike) -> dict:
    """What ``lsgan inspect`` prints: clips, frames, hours, captions, splits, labels and feature stats."""
    with Shard(path) as shard, reading(path, _SHARD):
        lengths = shard.lengths if len(shard) else np.zeros(1, np.int64)
        splits = {s: int((shard.splits == s).sum()) for s in sorted(set(shard.splits.tolist()))}
        actions: dict[str, int] = {}
        for a in shard.actions:
            key = shard.action_names[a] if a >= 0 else "(none)"
            actions[key] = actions.get(key, 0) + 1
        n_caps = sum(len(c) for c in shard._captions)
        return {
            "path": str(shard.path),
            "source": shard.source,
            "format_version": int(shard.attrs["format_version"]),
            "lsgan_version": str(shard.attrs.get("lsgan_version", "unknown")),
            "clips": len(shard),
            "mirrored": sum(1 for m in shard.mirror_of if m),
            "frames": int(lengths.sum()),
            "hours": float(lengths.sum() / shard.fps / 3600),
            "fps": shard.fps,
            "length_frames": {
                "min": int(lengths.min()), "median": float(np.median(lengths)), "max": int(lengths.max()),
            },
            "captions": n_caps,
            "clips_without_caption": sum(1 for c in shard._captions if not c),
            "splits": splits,
            "actions": dict(sorted(actions.items())),
            "stats_origin": str(shard.stats_origin),
            "mean_abs_mean": float(np.abs(shard.mean).mean()),
            "std_groups": [float(shard.std[i]) for i in (0, 1, 3, 4, 67, 193, 259)],
        }


def format_summary(info: dict) -> str:
    """A human-readable rendering of :func:`summarize`."""
    lines = [
        f"{info['path']}  (lsgan shard v{info['format_version']}, source {info['source']}, lsgan {info['lsgan_version']})",
        f"  clips      {info['clips']:,}  ({info['mirrored']:,} mirrored)",
        f"  frames     {info['frames']:,}  ({info['hours']:.2f} h at {info['fps']} fps);"
        f" length min {info['length_frames']['min']}, median {info['length_frames']['median']:.0f},"
        f" max {info['length_frames']['max']}",
        f"  captions   {info['captions']:,}  ({info['clips_without_caption']:,} clips without one)",
        "  splits     " + ", ".join(f"{k} {v:,}" for k, v in info["splits"].items()),
        f"  labels     {len([a for a in info['actions'] if a != '(none)'])}",
    ]
    lines += [f"    {name:<24} {count:,}" for name, count in info["actions"].items()]
    lines.append(f"  stats      {info['stats_origin']}; std per group " + ", ".join(f"{s:.4f}" for s in info["std_groups"]))
    return "\n".join(lines)
