"""What every process of a torchrun group needs, whether it trains (:mod:`fdnet.training.distributed`)
or describes a map (:mod:`fdnet.descriptors.sharding`): its place read from the environment, one
process reporting, and an exit that skips gloo's native teardown. Standard library only, so
inference code uses it without reaching training code."""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Iterator, Mapping

from fdnet.errors import ConfigError


def environment_int(environ: Mapping[str, str], name: str, default: int | None = None,
                    start: str = "start several processes") -> int:
    """The integer torchrun put in ``name``; ``default`` when it is absent (None: absent is an
    error saying how to ``start`` the processes)."""
    text = environ.get(name)
    if text is None:
        if default is None:
            raise ConfigError(f"WORLD_SIZE is set but {name} is not: {start} with torchrun "
                              "(it sets WORLD_SIZE, RANK, LOCAL_RANK, MASTER_ADDR and MASTER_PORT)")
        return default
    try:
        return int(text)
    except ValueError:
        raise ConfigError(f"environment variable {name}={text!r} is not an integer") from None


def require_rendezvous(environ: Mapping[str, str], world_size: int,
                       start: str = "start several processes") -> None:
    """ConfigError unless torchrun's rendezvous address is set (``env://`` needs both)."""
    missing = [name for name in ("MASTER_ADDR", "MASTER_PORT") if name not in environ]
    if missing:
        raise ConfigError(f"WORLD_SIZE={world_size} is set but {' and '.join(missing)} not: {start} with torchrun")


@contextlib.contextmanager
def quiet_unless(is_main: bool) -> Iterator[None]:
    """Standard output and the messages below WARNING (:mod:`fdnet.logs`) of the processes other
    than rank 0 go nowhere (their warnings and errors still reach standard error): one process
    reports, not N copies of it."""
    if is_main:
        yield
        return
    logger = logging.getLogger("fdnet")
    level = logger.level
    logger.setLevel(max(level, logging.WARNING))
    try:
        with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink):
            yield
    finally:
        logger.setLevel(level)


def leave(code: int) -> None:
    """Run the ``atexit`` handlers, flush the output and end by :func:`os._exit`.

    Why: after ``destroy_process_group`` a gloo process still holds native threads that C++ tears
    down at interpreter exit; now and then (a few runs in a hundred, more under load) one is still
    joinable then and the process dies of ``std::terminate`` (SIGABRT) after its work had finished
    and been saved, so torchrun reports a failure. Skipping the native teardown avoids it; nothing
    of ours is left to it."""
    import atexit
    import sys

    atexit._run_exitfuncs()  # what a normal exit would still run (logging handlers, temp files)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)
