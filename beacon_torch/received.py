"""Reading files that may come from someone else, within bounds.

A checkpoint, a policy, a cached start, a replay buffer's description or a results
summary may come from a colleague, a download or a shared disk. Its size on disk says
little of what reading it allocates (a compressed zip entry expands a thousandfold, a
small description can name a huge shape), so each file is checked against what it
claims to hold before anything of that size is allocated:

- a torch file (the zip archive ``torch.save`` writes) must be laid out as
  ``torch.save`` lays it out: every entry stored as it is, not compressed, and lying
  inside the file; the pickle of its structure at most :data:`PICKLE_BYTES`; every
  stored tensor used by that structure, and no tensor reaching past its stored bytes.
  It is read as tensors and plain values only (nothing in it runs), its tensors mapped
  from the file rather than read into memory, so that the caller's checks of their
  shapes against what the file claims to be (a network of a width, an env's state, a
  buffer of the run's capacity) run before any copy is made;
- a JSON or text record is read only up to the size its kind can have.

Each refusal is one line naming the file and what is wrong (:class:`BadFile`).
"""

from __future__ import annotations

import io
import json
import math
import pickle
import struct
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import nn

# The pickle of a file's structure (names, settings, which tensor is where; the tensors
# are stored apart) grows with the number of its tensors, not their size: the largest
# this library writes, a TD3 checkpoint with its optimiser states, is about 20 kB. A
# pickle of n bytes builds at most a few dozen times n bytes of Python objects.
PICKLE_BYTES = 4 * 2**20
# entries of an archive: a checkpoint holds under 100 tensors
MAX_ENTRIES = 10_000
# a small entry of torch.save's own (its format version, byte order, alignment)
SMALL_ENTRY = 4096
# a JSON record (a summary of trained seeds, a buffer's description): a summary of 50
# seeds with their training curves (200 points each at most) is about 0.6 MiB
JSON_BYTES = 2**20

_LOCAL_HEADER = struct.Struct("<4sHHHHHIIIHH")  # a zip entry's local header, 30 bytes


class BadFile(ValueError):
    """A file that is not what it claims to be, or holds more than that can: one line
    naming the file and the problem."""


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def size_of(path: str | Path, what: str, limit: int | None = None) -> int:
    """The size of the regular file ``path`` in bytes, refused above ``limit``."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError as err:
        raise FileNotFoundError(f"{path}: no readable {what} ({err.strerror or _first_line(err)})") from None
    if not path.is_file():
        raise BadFile(f"{path}: not a file, so not a {what}")
    if limit is not None and stat.st_size > limit:
        raise BadFile(f"{path}: {stat.st_size:,} bytes, more than a {what} holds (at most {limit:,})")
    return stat.st_size


def _entries(path: Path, size: int, what: str) -> dict[str, int]:
    """The entries of a torch archive and their sizes, refused unless laid out as
    ``torch.save`` writes them."""
    try:
        with zipfile.ZipFile(path) as archive, path.open("rb") as raw:
            infos = archive.infolist()
            if len(infos) > MAX_ENTRIES:
                raise BadFile(f"{path}: {len(infos):,} entries, more than a {what} holds")
            sizes, starts = {}, {}
            for info in infos:
                name = info.filename
                if info.compress_type != zipfile.ZIP_STORED or info.compress_size != info.file_size:
                    raise BadFile(
                        f"{path}: its entry {name!r} is compressed ({info.compress_size:,} bytes that expand "
                        f"to {info.file_size:,}); torch.save stores its entries as they are"
                    )
                raw.seek(info.header_offset)
                header = raw.read(_LOCAL_HEADER.size)
                if len(header) != _LOCAL_HEADER.size or header[:4] != b"PK\x03\x04":
                    raise BadFile(f"{path}: its entry {name!r} has no header where the archive says")
                name_len, extra_len = _LOCAL_HEADER.unpack(header)[-2:]
                start = info.header_offset + _LOCAL_HEADER.size + name_len + extra_len
                end = start + info.file_size
                if end > size:
                    raise BadFile(f"{path}: its entry {name!r} reaches past the end of the file ({end:,} > {size:,})")
                sizes[name] = info.file_size
                starts[name] = start
    except BadFile:
        raise
    # zipfile's own errors on a damaged directory: a bad archive, an entry name that is
    # not UTF-8, a method it cannot read, a field out of range
    except (zipfile.BadZipFile, UnicodeDecodeError, NotImplementedError, struct.error, ValueError, EOFError) as err:
        raise BadFile(f"{path}: not a {what} (not the archive torch.save writes: {_first_line(err)})") from None
    pickles = [name for name in sizes if name.endswith("/data.pkl") or name == "data.pkl"]
    if len(pickles) != 1:
        raise BadFile(f"{path}: not a {what} (an archive without the one structure torch.save writes)")
    if sizes[pickles[0]] > PICKLE_BYTES:
        raise BadFile(
            f"{path}: its structure takes {sizes[pickles[0]]:,} bytes, more than a {what} needs "
            f"(at most {PICKLE_BYTES:,})"
        )
    for name, n in sizes.items():
        if "/data/" not in name and not name.startswith("data/") and name != pickles[0] and n > SMALL_ENTRY:
            raise BadFile(f"{path}: its entry {name!r} takes {n:,} bytes, not one of torch.save's")
    # torch maps each stored tensor from where its entry starts, over as many bytes as
    # the structure declares: an entry shorter than that would lend it the next
    # entries' bytes
    with path.open("rb") as raw:
        raw.seek(starts[pickles[0]])
        structure = raw.read(sizes[pickles[0]])
    for entry, need in _declared_storages(path, structure, pickles[0], what).items():
        if entry not in sizes:
            raise BadFile(f"{path}: its structure names a stored tensor {entry!r} that the file does not hold")
        if sizes[entry] < need:
            raise BadFile(
                f"{path}: its stored tensor {entry!r} holds {sizes[entry]:,} bytes, fewer than the "
                f"{need:,} its shape needs"
            )
    return sizes


# bytes of an element of each storage kind a structure may name (torch.save records the
# legacy typed storage's class and the count of its elements)
_ELEMENT_BYTES = {
    "FloatStorage": 4,
    "DoubleStorage": 8,
    "HalfStorage": 2,
    "BFloat16Storage": 2,
    "LongStorage": 8,
    "IntStorage": 4,
    "ShortStorage": 2,
    "CharStorage": 1,
    "ByteStorage": 1,
    "BoolStorage": 1,
    "ComplexFloatStorage": 8,
    "ComplexDoubleStorage": 16,
}


class _Inert:
    """What every class and call in a structure read by :func:`_declared_storages`
    stands for: it accepts anything and does nothing."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def __setitem__(self, key, value) -> None:
        pass

    def __setstate__(self, state) -> None:
        pass

    def append(self, value) -> None:
        pass

    def extend(self, values) -> None:
        pass


class _StorageLister(pickle.Unpickler):
    """Reads a structure's pickle only to list the storages it names: every class it
    names is an inert stand-in (nothing is imported, nothing it names runs)."""

    def __init__(self, data: bytes) -> None:
        super().__init__(io.BytesIO(data))
        self.storages: list[tuple] = []

    def find_class(self, module: str, name: str):
        return type(str(name)[:100], (_Inert,), {"origin": f"{module}.{name}"[:200]})

    def persistent_load(self, pid):
        self.storages.append(tuple(pid) if isinstance(pid, tuple) else (pid,))
        return _Inert()


def _declared_storages(path: Path, data: bytes, archive_pickle: str, what: str) -> dict[str, int]:
    """The stored tensors that the structure of a torch archive (``data``, its entry
    ``archive_pickle``) names, by entry, with the bytes each declares (its elements
    times their size)."""
    lister = _StorageLister(data)
    try:
        lister.load()
    except Exception as err:  # a damaged pickle: the stand-ins themselves raise nothing
        raise BadFile(f"{path}: not a {what} (its structure is unreadable: {_first_line(err)[:120]})") from None
    prefix = archive_pickle[: -len("data.pkl")]
    declared: dict[str, int] = {}
    for pid in lister.storages:
        kind = getattr(pid[1], "origin", "") if len(pid) == 5 else ""
        name = kind.removeprefix("torch.")
        if pid[0] != "storage" or name not in _ELEMENT_BYTES or not isinstance(pid[2], str):
            raise BadFile(f"{path}: not a {what} (its structure names a stored value of an unknown kind)")
        numel = pid[4]
        if isinstance(numel, bool) or not isinstance(numel, int) or numel < 0:
            raise BadFile(f"{path}: not a {what} (a stored tensor of {numel!r} elements)")
        entry = f"{prefix}data/{pid[2]}"
        declared[entry] = max(declared.get(entry, 0), numel * _ELEMENT_BYTES[name])
    return declared


def tensors_in(tree: Any) -> list[torch.Tensor]:
    """Every tensor in nested dicts, lists and tuples."""
    if isinstance(tree, torch.Tensor):
        return [tree]
    if isinstance(tree, dict):
        return [t for v in tree.values() for t in tensors_in(v)]
    if isinstance(tree, (list, tuple)):
        return [t for v in tree for t in tensors_in(v)]
    return []


def _copied(tree: Any) -> Any:
    """``tree`` with every tensor copied into memory of its own (off the file)."""
    if isinstance(tree, torch.Tensor):
        return tree.clone(memory_format=torch.contiguous_format)
    if isinstance(tree, dict):
        return type(tree)((k, _copied(v)) for k, v in tree.items())
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):
        return type(tree)(*(_copied(v) for v in tree))
    if isinstance(tree, (list, tuple)):
        return type(tree)(_copied(v) for v in tree)
    return tree


def torch_file(path: str | Path, what: str, check: Callable[[Any], None] | None = None) -> Any:
    """The contents of a file written by ``torch.save`` (``what`` it should be, for the
    messages), read within bounds (see the module's docstring): tensors and plain
    values only. ``check(contents)`` runs while the tensors are still mapped from the
    file, before any is copied into memory; it raises an error naming the file for
    contents that are not what the file claims."""
    path = Path(path)
    size = size_of(path, what)
    sizes = _entries(path, size, what)
    try:
        contents = torch.load(path, weights_only=True, mmap=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        # torch's message explains how to load the file anyway, running its code: only
        # its line naming what was refused is kept
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        found = next((line for line in lines if "GLOBAL" in line or "Unsupported" in line), "")
        found = found.split("error:", 1)[-1].strip() or "objects that are not tensors or plain values"
        raise BadFile(
            f"{path}: not a {what}: it holds more than tensors and plain values, and is refused "
            f"(loading it could run code; {found[:200]})"
        ) from None
    except Exception as err:  # a truncated or foreign file: torch's own errors name no file
        raise BadFile(f"{path}: unreadable {what} ({type(err).__name__}: {_first_line(err)[:200]})") from None
    stored = sum(n for name, n in sizes.items() if "/data/" in name or name.startswith("data/"))
    used, seen = 0, set()
    for t in tensors_in(contents):
        storage = t.untyped_storage()
        if t.numel() and t.storage_offset() * t.element_size() + _reach(t) > storage.nbytes():
            raise BadFile(f"{path}: a tensor of shape {tuple(t.shape)} reaches past its stored values")
        if storage.data_ptr() not in seen:
            seen.add(storage.data_ptr())
            used += storage.nbytes()
    if used < stored:
        raise BadFile(f"{path}: {stored - used:,} of its {stored:,} stored bytes belong to no value it holds")
    if check is not None:
        check(contents)
    return _copied(contents)


def _reach(t: torch.Tensor) -> int:
    """Bytes from a tensor's first element to the end of its last one; a tensor that
    repeats an element (a zero stride) counts as if it were laid out densely, since
    every use of it, a copy included, allocates that much."""
    if any(s == 0 for s, n in zip(t.stride(), t.shape, strict=True) if n > 1):
        return t.numel() * t.element_size()
    return (1 + sum((n - 1) * abs(s) for n, s in zip(t.shape, t.stride(), strict=True))) * t.element_size()


def load_into(module: nn.Module, weights: dict, name: str, network: str) -> None:
    """Load ``weights`` (a state dict) into ``module``, refusing (one line starting with
    ``name``) other entries, other shapes, or values that are not finite once cast to
    the module's dtype."""
    own = module.state_dict()
    if set(own) != set(weights):
        missing, extra = sorted(set(own) - set(weights)), sorted(set(weights) - set(own))
        raise ValueError(f"{name} are not those of {network} (missing {missing[:3]}, unknown {extra[:3]})")
    for key, value in weights.items():
        if not isinstance(value, torch.Tensor) or value.shape != own[key].shape:
            shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            own_shape = tuple(own[key].shape)
            raise ValueError(f"{name} do not fit {network}: {key} has shape {shape}, the network's {own_shape}")
        if value.is_complex() or (own[key].is_floating_point() and value.dtype == torch.bool):
            raise ValueError(f"{name} do not fit {network}: {key} holds {value.dtype} values")
    module.load_state_dict(weights)
    for key, value in module.state_dict().items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name}: {key} has non-finite values in {value.dtype}")


def text_file(path: str | Path, what: str, limit: int) -> str:
    """The text of the regular file ``path`` (UTF-8), of at most ``limit`` bytes; a
    device, a FIFO or a folder is refused before anything is read from it."""
    path = Path(path)
    size_of(path, what, limit)
    try:
        with path.open("rb") as f:
            data = f.read(limit + 1)  # a file that grew since its size was taken
    except OSError as err:
        raise BadFile(f"{path}: unreadable {what} ({err.strerror or _first_line(err)})") from None
    if len(data) > limit:
        raise BadFile(f"{path}: more than a {what} holds (at most {limit:,} bytes)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise BadFile(f"{path}: not a {what} (not UTF-8 text)") from None


def json_file(path: str | Path, what: str, limit: int = JSON_BYTES) -> Any:
    """A JSON file of at most ``limit`` bytes; numbers beyond a float's range read as
    what JSON means by them (``1e400`` is infinite), which the caller's checks refuse."""
    text = text_file(path, what, limit)
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as err:
        raise BadFile(f"{path}: unreadable {what} ({type(err).__name__}: {_first_line(err)[:200]})") from None


def finite_number(value: Any) -> bool:
    """Whether ``value`` is an int or float (not a bool) that a float holds finitely
    (``10**400`` does not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False
