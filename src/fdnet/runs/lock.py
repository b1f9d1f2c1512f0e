"""The run lock: one training at a time writes to a run directory (``RUN_DIR/.lock``)."""

from __future__ import annotations

import datetime
import os
import socket
import time
from pathlib import Path

import yaml

from fdnet.errors import ConfigError, output_error

try:
    import fcntl
except ImportError:  # Windows: loading runs works; RunLock says it cannot lock (see there)
    fcntl = None

LOCK_FILE = ".lock"


def local_time_stamp() -> str:
    """Now, in local time with its offset, to the second: what run records and locks say."""
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


class RunLock:
    """Exclusive lock on a run directory while a training writes to it.

    ``fcntl.flock(LOCK_EX | LOCK_NB)`` on ``run_dir/.lock``, which then holds the holder's pid,
    host and command. A second holder (another process, or a second RunLock in this one) gets a
    ConfigError naming the holder. The kernel drops the lock when its process ends, kill -9
    included, so a stale ``.lock`` file never blocks a resume. The file is never deleted: deleting
    a lock file lets two processes lock two different files of the same name. Processes forked
    while the lock is held (DataLoader workers) share it until they exit too.
    """

    def __init__(
        self, run_dir: str | Path, command: str = "fdnet train", lock_file: str = LOCK_FILE, subject: str | None = None
    ):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / lock_file
        self.command = command
        #: what the messages say is in use (default: the run directory)
        self.subject = subject or str(self.run_dir)
        self._fd: int | None = None

    @classmethod
    def for_file(cls, path: str | Path, command: str) -> "RunLock":
        """The lock of one output file that a run writes over a long time and may resume
        (``fdnet loop-closure``'s events): ``.NAME.lock`` beside it."""
        path = Path(path)
        return cls(path.parent, command, lock_file=f".{path.name}.lock", subject=str(path))

    def _holder(self) -> dict:
        # The holder writes its details right after locking; give it a moment if we came between.
        for _ in range(10):
            try:
                data = yaml.safe_load(self.path.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, yaml.YAMLError):
                data = None
            if isinstance(data, dict) and "pid" in data:
                return data
            time.sleep(0.02)
        return {}

    def acquire(self) -> "RunLock":
        if self._fd is not None:
            raise RuntimeError(f"{self.path}: this RunLock is already held")
        if fcntl is None:
            raise ConfigError(
                f"{self.run_dir}: cannot lock the run directory on this platform " "(needs fcntl: Linux, macOS)"
            )
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(str(self.path), os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise output_error(
                f"{self.path}: cannot create the run directory's lock file " f"({exc.strerror or exc})", exc
            ) from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            os.close(fd)
            holder = self._holder()
            if not holder:
                raise ConfigError(
                    f"{self.subject} is in use by another process (see {self.path}); "
                    "wait for it to finish or stop it"
                ) from exc
            where = "" if holder.get("host") in (None, socket.gethostname()) else f" on {holder['host']}"
            raise ConfigError(
                f"{self.subject} is in use by process {holder.get('pid')}{where} "
                f"({holder.get('command', '?')}, started {holder.get('started', '?')}); "
                "wait for it to finish or stop it"
            ) from exc
        except OSError as exc:
            os.close(fd)
            raise ConfigError(
                f"{self.path}: cannot lock the run directory ({exc.strerror or exc}); "
                "its filesystem may not support file locks"
            ) from exc
        info = yaml.safe_dump(
            {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command, "started": local_time_stamp()},
            sort_keys=False,
        )
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, info.encode("utf-8"), 0)
        except OSError as exc:  # a full disk: name the file (the error from pwrite names none)
            os.close(fd)
            raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            os.ftruncate(fd, 0)  # no stale holder details once the run is free
        finally:
            os.close(fd)  # releases the flock

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc_info) -> None:
        self.release()
