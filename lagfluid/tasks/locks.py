"""Locks on what a run writes: a second run into the same outputs is refused with one line naming the first.

A lock is ``fcntl.flock`` on a small file beside the outputs (``.lagfluid.lock`` for a whole folder,
``.lagfluid-<unit>.lock`` for a part of one: a trainable's files in a ``task=train`` folder, one scene of a
dataset). The kernel releases it when its process ends, however it ends (``kill -9`` too), so no lock is ever
left held. The file records its holder (pid, host, task, command, start time) for the line a refused run
prints; the holder removes it when it ends. A file a killed run left behind (no process holds its lock) is
taken over, and the log says whose it was.

Taking a lock writes nothing but its own file, and a refused run touches nothing: :class:`OutDirCheck` stops a
command whose folder a live run holds before Hydra writes its ``.hydra/`` files there.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
import os
import socket
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from lagfluid.errors import LagfluidError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: runs are not locked there
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

_COMMAND_CHARS = 160  # of the holder's command line in the refusal: the line stays one screen line or two


class OutputsInUse(LagfluidError):
    """Another live run holds the lock on the outputs this run would write."""


def lock_path(folder: Path, unit: str = "") -> Path:
    """The lock file of ``folder`` (``unit=""``) or of one ``unit`` of it (a trainable, a scene)."""
    return folder / (f".lagfluid-{unit}.lock" if unit else ".lagfluid.lock")


def _record(task: str) -> str:
    """This process as a lock holder: pid, host, task, command line and start time (one JSON line)."""
    command = " ".join(sys.argv[1:])  # the overrides: python -m lagfluid.run's own path says nothing
    since = dt.datetime.now().astimezone().isoformat(sep=" ", timespec="seconds")
    holder = {"pid": os.getpid(), "host": socket.gethostname(), "task": task, "command": command}
    return json.dumps({**holder, "since": since}) + "\n"


def describe_holder(text: str) -> str:
    """A lock file's record as ``pid 12 on host (task=simulate: command), since ...``, for a message."""
    try:
        holder = json.loads(text)
        command = str(holder.get("command", ""))
        if len(command) > _COMMAND_CHARS:
            command = command[: _COMMAND_CHARS - 3] + "..."
        return (
            f"pid {holder['pid']} on {holder.get('host', '?')} (task={holder.get('task', '?')}"
            f"{': ' + command if command else ''}), since {holder.get('since', '?')}"
        )
    except (ValueError, KeyError, TypeError, AttributeError):  # empty (it is just being written) or foreign
        return "a run that has not said who it is yet"


def _holder(path: Path) -> str:
    """:func:`describe_holder` of the lock file ``path``."""
    try:
        return describe_holder(path.read_text(errors="replace"))
    except OSError:  # released meanwhile
        return describe_holder("")


def _in_use(folder: Path, unit: str, what: str) -> OutputsInUse:
    """The refusal: which outputs, who holds them, what to do (``what``: the key that names ``folder``)."""
    part = f" ({unit})" if unit else ""
    other = "" if what == "run" else f" or choose another {what}"  # an export has no other run to choose
    return OutputsInUse(
        f"{what} {folder}{part} is in use by another run: {_holder(lock_path(folder, unit))}; wait for it to "
        f"end{other}"
    )


def _open_locked(path: Path, wait: bool) -> int | None:
    """A descriptor of ``path`` holding its exclusive lock, or None when another process holds it (no wait).

    A holder removes the file when it ends: a descriptor of the removed file is dropped and ``path`` tried
    again, so two runs never hold locks on two files of one name.
    """
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        except BaseException:
            os.close(fd)
            raise
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def _take(fd: int, path: Path, task: str) -> None:
    """Write this process's record into the locked file; say so when it held a killed run's record."""
    left = os.read(fd, 4096).decode(errors="replace").strip()
    if left:
        log.warning(
            "%s: took over the lock of %s, which ended without releasing it", path, describe_holder(left)
        )
    os.ftruncate(fd, 0)
    os.pwrite(fd, _record(task).encode(), 0)


def _release(fd: int, path: Path) -> None:
    """Remove the lock file (while still holding it), then let go of the lock."""
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    os.close(fd)


@contextlib.contextmanager
def hold_outputs(
    folder: Path, task: str, units: Sequence[str] = ("",), what: str = "out_dir"
) -> Iterator[None]:
    """Hold the locks of ``units`` of ``folder`` (made if missing) for the ``with`` block, or refuse at once.

    Args:
        folder: the folder the run writes into.
        task: the running task, for the holder's record (``simulate``, ``train``, ...).
        units: the parts of ``folder`` this run writes (``""``: all of it).
        what: the key that names ``folder``, for the refusal (``out_dir``, ``data.out_dir``, ``run``).

    Raises:
        OutputsInUse: a live process holds one of the locks; the message names it. Nothing this call took is
            kept, and nothing else in ``folder`` was touched.
    """
    if fcntl is None:  # pragma: no cover - not POSIX
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    held: list[tuple[int, Path]] = []
    try:
        for unit in units:
            path = lock_path(folder, unit)
            fd = _open_locked(path, wait=False)
            if fd is None:
                raise _in_use(folder, unit, what)
            held.append((fd, path))
            _take(fd, path, task)
        yield
    finally:
        for fd, path in reversed(held):
            _release(fd, path)


@contextlib.contextmanager
def wait_for_lock(path: Path, task: str, what: str) -> Iterator[None]:
    """Hold the lock file ``path`` for the ``with`` block, waiting for its holder (logged once, by name).

    Args:
        path: the lock file (its folder must exist).
        task: the running task, for the holder's record.
        what: what the lock guards, for the log line ("the MPS reference in DIR").
    """
    if fcntl is None:  # pragma: no cover - not POSIX
        yield
        return
    fd = _open_locked(path, wait=False)
    if fd is None:
        log.info("waiting for %s: %s holds its lock", what, _holder(path))
        fd = _open_locked(path, wait=True)
    try:
        _take(fd, path, task)
        yield
    finally:
        _release(fd, path)


def check_out_dir(folder: Path) -> None:
    """Refuse now, only reading, when a live run holds ``folder``'s lock (before Hydra writes files there).

    Raises:
        OutputsInUse: as :func:`hold_outputs` would.
    """
    path = lock_path(folder)
    if fcntl is None or not path.is_file():
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # gone meanwhile, or unreadable: the task's own lock decides
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise _in_use(folder, "", "out_dir") from None
    finally:
        os.close(fd)  # a shared lock we got goes with the descriptor


class OutDirCheck(Callback):
    """Hydra callback (``conf/config.yaml``): a run into a folder a live run holds stops with one line.

    ``on_run_start`` comes before Hydra writes ``.hydra/`` and the log into the run's folder; the task's own
    lock (:func:`hold_outputs`) then decides for good. A multirun's jobs each write into a folder of theirs.
    """

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Exit with status 1 and one line when a live run holds ``hydra.run.dir`` (the ``out_dir``)."""
        try:
            folder = Path(str(config.hydra.run.dir))
        except Exception:  # an interpolation that fails: Hydra reports it itself, in its own words
            return
        try:
            check_out_dir(folder)
        except OutputsInUse as err:
            sys.stderr.write(f"lagfluid: {err}\n")
            sys.exit(1)
