"""Writing files next to files that may come from someone else.

A run directory, a results summary or a downloaded archive is untrusted input: a
symbolic link planted in it would make a command that writes a file of the same name
write wherever the link points. So the commands refuse a directory that holds a link
before they touch it, and write every file under a fresh temporary name (created here,
never followed) that then replaces the target in one step: a replaced link is the link
itself, not what it pointed to.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import tempfile
import time
import weakref
from collections.abc import Callable
from pathlib import Path

try:
    import fcntl
except ImportError:  # not on Windows: no lock there
    fcntl = None


class UnsafeFile(ValueError):
    """A file or directory that a command refuses to read or write (a planted link, a
    directory another run holds)."""


# the folders an experiment tracker keeps in a run directory, with links of its own
# (Weights & Biases' ``latest-run``); nothing of this library reads or writes there
TRACKER_FOLDERS = ("wandb",)


def refuse_links(root: str | Path) -> None:
    """Refuse ``root`` when a symbolic link lies anywhere below it (``root`` itself may
    be one: the user names it), outside the experiment trackers' own folders."""
    for folder, dirs, names in os.walk(root):  # links to folders are listed, not entered
        if Path(folder) == Path(root):
            dirs[:] = [d for d in dirs if d not in TRACKER_FOLDERS or (Path(folder) / d).is_symlink()]
        for name in (*dirs, *names):
            path = Path(folder) / name
            if path.is_symlink():
                raise UnsafeFile(
                    f"{path}: a symbolic link inside {root} is refused (a command writing there "
                    f"would write where it points); remove it"
                )


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _temporary(path: Path) -> Path:
    """A new empty file beside ``path`` with the permissions a file created there by
    ``open`` would have (the umask's, not a temporary file's owner-only ones), under a
    name short enough for any name ``path`` may have."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".", suffix=f"-{path.name[:64]}.partial")
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())
    return Path(tmp)


def replace_file(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Write ``path`` by ``write(temporary)`` into a new file beside it, then put that
    file in its place in one step: a reader never sees half a file, a stop keeps the
    previous one, and a link at ``path`` is replaced, not followed."""
    path = Path(path)
    tmp = _temporary(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def save_tensors(obj, path: str | Path) -> Path:
    """:func:`replace_file` with ``torch.save(obj)``; a write that fails (a full disk)
    is an :class:`OSError` naming the file and the space left, and leaves the previous
    file as it was."""
    import torch

    path = Path(path)
    try:
        return replace_file(path, lambda tmp: torch.save(obj, tmp))
    except (RuntimeError, OSError) as err:  # torch reports a failed write as a RuntimeError
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        try:
            left = f"{free_bytes(path.parent) / 2**20:,.1f} MiB free there"
        except OSError:
            left = "its folder is unreadable"
        raise OSError(f"{path}: could not be written ({first[:160]}; {left}); the previous file is kept") from None


def create_file(path: str | Path, write: Callable[[Path], object], hint: str = "") -> Path:
    """Write a new file at ``path`` by ``write(temporary)``, refusing one that exists
    (:class:`FileExistsError`, naming it and ``hint``): the file appears whole or not at
    all, and whatever was there, a file or a link, is left as it was."""
    path = Path(path)
    refuse_existing([path], hint)
    tmp = _temporary(path)
    try:
        write(tmp)
        try:
            os.link(tmp, path)  # fails if the name was taken meanwhile: never replaces
        except FileExistsError:
            refuse_existing([path], hint)
            raise
    finally:
        tmp.unlink(missing_ok=True)
    return path


def refuse_existing(paths, hint: str = "") -> None:
    """:class:`FileExistsError` for the first of ``paths`` that exists (or is a link):
    a command checks the files it will write before its work, not after."""
    for path in map(Path, paths):
        if path.exists() or path.is_symlink():
            raise FileExistsError(f"{path} exists and is not overwritten" + (f"; {hint}" if hint else ""))


def free_names(*paths: str | Path) -> list[Path]:
    """``paths`` themselves when none exists, else each with the same first free number
    (``run-2.png``, ``scores-2.json``): default output names that never replace a file."""
    paths = [Path(p) for p in paths]
    for n in range(1, 10_000):
        named = paths if n == 1 else [p.with_name(f"{p.stem}-{n}{p.suffix}") for p in paths]
        if not any(p.exists() or p.is_symlink() for p in named):
            return named
    raise FileExistsError(f"{paths[0].parent}: no free name for {', '.join(p.name for p in paths)}")


def outputs(given: str | Path | None, default: str | Path, *names: str, option: str = "--out") -> list[Path]:
    """The files a command writes: in (or at) the place the user ``given``, refused there
    if any exists; at the ``default`` place, under free names (:func:`free_names`). A
    command calls it before its work, so that nothing is lost to a refusal at the end."""
    place = Path(given if given is not None else default)
    paths = [place / n for n in names] if names else [place]
    if given is not None:
        refuse_existing(paths, f"give a new {option} (nothing is overwritten)")
        return paths
    return free_names(*paths)


def dated_name(stem: str, suffix: str = "") -> str:
    """``stem-YYYYmmdd-HHMMSS`` + ``suffix``: a name for a new record of a measurement."""
    return f"{stem}-{time.strftime('%Y%m%d-%H%M%S')}{suffix}"


def write_text(path: str | Path, text: str) -> Path:
    """:func:`replace_file` with ``text``."""
    return replace_file(path, lambda tmp: tmp.write_text(text))


def save_figure(fig, path: str | Path, *, new: bool = False) -> Path:
    """:func:`replace_file` with a matplotlib figure, in the format of the name's
    suffix; with ``new``, :func:`create_file` (a file that appeared meanwhile is
    refused, not replaced)."""
    path = Path(path)
    write = lambda tmp: fig.savefig(tmp, format=path.suffix.lstrip(".") or "png")
    return create_file(path, write) if new else replace_file(path, write)


def new_folder(parent: str | Path, name: str) -> Path:
    """A new empty folder in ``parent`` whose name ends with ``name``, created here (so
    that nothing planted under that name is written into)."""
    folder = Path(tempfile.mkdtemp(dir=parent, prefix=".", suffix=f"-{name[:64]}"))
    folder.chmod(0o777 & ~_umask())
    return folder


def remove_partials(folder: str | Path) -> None:
    """Remove what :func:`replace_file` and :func:`new_folder` left behind in
    ``folder`` when a process stopped half way (never links: :func:`refuse_links`
    runs first)."""
    for path in Path(folder).glob(".*.partial"):
        if path.is_symlink():
            continue
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()


def free_bytes(folder: str | Path) -> int:
    return shutil.disk_usage(folder).free


class Lock:
    """An exclusive lock on ``folder`` while this object lives (or until
    :meth:`release`): a second process asking for it is refused at once. The kernel
    drops it when the process dies, so a killed run never leaves a stale lock."""

    NAME = ".lock"
    _held: weakref.WeakValueDictionary[str, Lock] = (
        weakref.WeakValueDictionary()
    )  # per folder, the lock this process holds

    def __init__(self, folder: str | Path) -> None:
        self.path = Path(folder) / self.NAME
        self.key, self.fd = str(self.path.resolve()), None
        earlier = Lock._held.pop(self.key, None)
        if earlier is not None:  # a run of this process that ended without closing
            earlier.release()
        if self.path.is_symlink():
            raise UnsafeFile(f"{self.path}: a symbolic link is refused")
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise UnsafeFile(
                    f"{folder}: another process is running in this directory (its lock {self.path} "
                    f"is held); wait for it or give a new directory"
                ) from None
        self.fd = fd
        Lock._held[self.key] = self

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
        if Lock._held.get(self.key) is self:
            Lock._held.pop(self.key, None)

    def __del__(self) -> None:
        self.release()


def machine() -> str:
    """A one-line description of where the numbers come from."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import torch

    text = f"{cpu}, {torch.get_num_threads()} threads, torch {torch.__version__}, Python {platform.python_version()}"
    if torch.cuda.is_available():
        text += f", GPU {torch.cuda.get_device_name()}"
    return text


def revision(tree: str | Path) -> str | None:
    """The commit a source tree is checked out at, with ``+changes`` where its tracked
    files differ from it; None where it is no git checkout (or git is missing). A record
    that compares two trees names their commits, which outlive the folders."""
    import subprocess

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(
                ["git", "-C", str(tree), *args], capture_output=True, text=True, timeout=30, check=False
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit is None:
        return None
    return commit + ("+changes" if git("status", "--porcelain", "--untracked-files=no") else "")


def save_rows(rows: list[dict], out: str | Path, name: str) -> Path:
    """``rows`` with the machine they were measured on, as a new dated file
    ``out/name-YYYYmmdd-HHMMSS.json`` (an earlier record is never replaced)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"machine": machine(), "rows": rows}, indent=1)
    return create_file(out / dated_name(name, ".json"), lambda tmp: tmp.write_text(text))
