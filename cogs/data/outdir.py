"""Output folders that never lose what a user has.

A command that writes a folder (`cogs synth`, `cogs import`, `cogs preprocess`, the demo's
scene) checks its `--out` before any work (`check_out_folder`), writes everything into a
temporary sibling folder, and puts that in place only once it is complete and accepted
(`put_in_place`): an interrupted or failed run never leaves half a scene under the user's
name, and a folder that is replaced (only with the user's say-so) is removed only after its
replacement is in place. While it works, the command holds `--out` (`claimed`): a second
cogs command given the same folder stops at once instead of clearing the first one's
temporary folder or checkpoints.
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from cogs.errors import UserError

log = logging.getLogger("cogs")

MARKER = ".cogs-staging"
"""Written into every temporary folder cogs makes: only such folders are ever reused or removed."""


def describe(path: Path) -> str:
    """A short account of what `path` holds, for messages ("a cogs scene 'synth' (100 frames,
    written by cogs.data.synth)", "a folder of 12 files")."""
    from cogs.data.io import read_json

    try:
        meta = read_json(path / "scene.json")
        if isinstance(meta, dict):
            src = meta.get("source") if isinstance(meta.get("source"), dict) else {}
            who = src.get("generator") or src.get("tool") or src.get("importer")
            frames = meta.get("frames")
            parts = [f"{len(frames)} frames" if isinstance(frames, list) else None, f"written by {who}" if who else None]
            inner = ", ".join(p for p in parts if p)
            return f"a cogs scene {meta.get('name', path.name)!r}" + (f" ({inner})" if inner else "")
    except (OSError, ValueError, RecursionError):
        pass
    try:
        n = sum(len(files) for _, _, files in os.walk(path))
    except OSError:
        return "a folder"
    return f"a folder of {n} file{'s' if n != 1 else ''}"


def is_empty_folder(path: Path) -> bool:
    try:
        with os.scandir(path) as it:
            return next(it, None) is None
    except OSError:
        return False


def check_out_folder(path: Path, option: str = "--out", overwrite: bool = False, hint: str = "") -> bool:
    """Before any work: may `path` be written as a new folder? True when something is there
    that will be replaced (only allowed with `overwrite`). UserError naming `option` when
    `path` is a file, sits under a file, or holds something and `overwrite` is off."""
    path = Path(path)
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise UserError(f"{option} {path}: {parent} is a file, not a folder")
    if os.path.islink(path) and not path.exists():
        raise UserError(f"{option} {path} is a broken symbolic link")
    if not path.exists():
        return False
    if not path.is_dir():
        raise UserError(f"{option} {path} is an existing file; {option} names a folder to write")
    if is_empty_folder(path):
        return False
    if not overwrite:
        raise UserError(
            f"{option} {path} already holds {describe(path)}; cogs does not write over it. "
            f"Choose another {option}, delete it, or pass --overwrite to replace it once the new result is complete"
            + (f" ({hint})" if hint else "")
        )
    return True


def check_out_file(path: Path, suffixes: tuple[str, ...], option: str = "--out") -> None:
    """Before any work: `path` can be written as a file of one of `suffixes` (an existing
    file there is replaced, as a re-run expects). UserError naming the option otherwise."""
    if path.is_dir():
        raise UserError(f"{option} {path} is an existing folder; {option} names the file to write")
    if path.suffix.lower() not in suffixes:
        raise UserError(f"{option} {path}: unknown extension {path.suffix or '(none)'!r}; use one of {', '.join(suffixes)}")
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise UserError(f"{option} {path}: {parent} is a file, not a folder")


def staging_folder(out: Path, suffix: str) -> Path:
    return out.parent / f"{out.name}{suffix}"


def new_staging(path: Path) -> Path:
    """An empty staging folder at `path`; one cogs left there earlier is cleared, anything
    else is refused (never removed)."""
    if path.exists() or os.path.islink(path):
        if not (path.is_dir() and (path / MARKER).exists()):
            raise UserError(f"{path} is in the way: cogs needs this name for its temporary folder and did not "
                            "make what is there; move or delete it")
        shutil.rmtree(path)
    path.mkdir(parents=True)
    (path / MARKER).write_text("a temporary folder of cogs; safe to delete\n")
    return path


def put_in_place(staged: Path, out: Path) -> str | None:
    """Move the finished folder `staged` to `out`. Whatever `out` held is moved aside first
    and removed only once `staged` is in place; returns its description (None when there
    was nothing)."""
    (staged / MARKER).unlink(missing_ok=True)
    replaced = None
    if os.path.islink(out) or out.exists():
        if out.is_dir() and not os.path.islink(out) and is_empty_folder(out):
            out.rmdir()
        else:
            replaced = describe(out)
            aside = out.parent / f".{out.name}.replaced-{uuid.uuid4().hex[:8]}"
            os.rename(out, aside)
            try:
                os.rename(staged, out)
            except OSError:
                os.rename(aside, out)
                raise
            if aside.is_dir() and not os.path.islink(aside):
                shutil.rmtree(aside, ignore_errors=True)
            else:
                aside.unlink(missing_ok=True)
            return replaced
    out.parent.mkdir(parents=True, exist_ok=True)
    os.rename(staged, out)
    return replaced


@contextmanager
def staged(out: Path, accept=None):
    """Write a folder for `out` in a temporary sibling (yielded); when the block ends without
    an error and `accept(folder)` (if given) returns no problems, it replaces `out` (see
    `put_in_place`, whose result is in `.replaced` of the yielded path's holder). On any
    error the temporary folder is removed and `out` is untouched. The caller checks `out`
    first (`check_out_folder`)."""
    with claimed(out):
        tmp = new_staging(out.parent / f".{out.name}.cogs-tmp")
        holder = _Staged(tmp)
        try:
            yield holder
            if accept is not None:
                accept(tmp)
            holder.replaced = put_in_place(tmp, out)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)


class _Staged:
    def __init__(self, path: Path):
        self.path = path
        self.replaced: str | None = None


# -- one writer per folder ----------------------------------------------------------------

LOCK_SUFFIX = ".cogs-lock"
_held: dict[str, int] = {}  # lock file -> how many `claimed` blocks of this process hold it


def lock_file(out: Path) -> Path:
    """The file beside `out` whose lock says a cogs command is writing `out`."""
    out = Path(os.path.abspath(out))
    return out.parent / f".{out.name}{LOCK_SUFFIX}"


@contextmanager
def claimed(out: Path, option: str = "--out") -> Iterator[None]:
    """Hold `out` for this process while the block writes it (its temporary sibling, its
    checkpoints, its replacement). A second process claiming the same folder gets a
    UserError at once naming the process that holds it: two runs on one `--out` would
    otherwise clear each other's temporary folder and end in a traceback or a mixed result.

    The claim is an advisory `flock` on `.<name>.cogs-lock` beside `out`, which the kernel
    releases when the process ends however it ends (a file left by a killed run is simply
    claimed again). Nested claims of one folder in one process are one claim. Where `flock`
    does not exist (Windows) the block runs unclaimed."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    path = lock_file(out)
    key = str(path)
    if key in _held:
        _held[key] += 1
        try:
            yield
        finally:
            _held[key] -= 1
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UserError(f"{option} {out}: cannot create {path.parent} ({e.strerror})") from None
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise UserError(f"{option} {out}: cannot write beside it in {path.parent} ({e.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
            os.close(fd)
            who = f"process {holder}" if holder.isdigit() else "another process"
            raise UserError(f"{option} {out} is being written by another cogs command ({who}); wait for it to finish "
                            f"or choose another {option}") from None
        except OSError as e:  # a file system without locks (some network mounts): work unclaimed, as before
            os.close(fd)
            path.unlink(missing_ok=True)
            log.warning("%s %s: cannot lock %s (%s); another cogs command on the same folder would not be stopped",
                        option, out, path, e.strerror)
            yield
            return
        # The holder before us may have removed the file between our open and our lock:
        # then we hold a lock on a file nobody else will see; take the one at `path`.
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    _held[key] = 1
    try:
        yield
    finally:
        del _held[key]
        try:
            path.unlink()  # still holding the lock, so nobody else holds this file
        except OSError:
            pass
        os.close(fd)
