"""Errors a user can act on.

Anything raised as :class:`FdnetError` is printed by the CLI as one clear line (no traceback):
the message must name the file (and line, where there is one) and what is wrong with it.
"""


class FdnetError(Exception):
    """Base class: a problem with the user's input, data or configuration."""


class DataError(FdnetError):
    """An image, folder or ground-truth file that cannot be used as it is."""


class ConfigError(FdnetError):
    """A setting, preset, checkpoint or command-line combination that cannot work."""


class OutputError(ConfigError, OSError):
    """An output that cannot be written (a full disk, a read-only folder). Also an OSError, so
    code that tolerates a failed write (a cache) still does."""


def output_error(message: str, cause: OSError) -> OutputError:
    """``message`` as an :class:`OutputError` with the errno of the operating system's ``cause``
    (ENOSPC for a full disk), so callers can still tell why the write failed."""
    error = OutputError(message)
    error.errno = cause.errno
    return error


#: operating-system errors that are about the user's disk, folders or names, not a bug: the CLI
#: prints them as one line naming the path (see :func:`os_error_message`)
_ENVIRONMENT_ERRNOS = {
    "ENOSPC": "no space left on the device",
    "EDQUOT": "disk quota exceeded",
    "EFBIG": "file too large for the file system",
    "EROFS": "read-only file system",
    "EACCES": "permission denied",
    "EPERM": "operation not permitted",
    "ENAMETOOLONG": "file name too long",
    "EISDIR": "is a directory",
    "ENOTDIR": "a part of the path is not a directory",
    "ENOENT": "no such file or directory",
    "EIO": "input/output error (a failing disk or a disconnected network share)",
    "EMFILE": "too many open files",
    "ENFILE": "too many open files in the system",
}
#: errors that only a write meets
_WRITE_ERRNO_NAMES = {"ENOSPC", "EDQUOT", "EFBIG", "EROFS"}


def os_error_message(exc: BaseException, outputs: tuple = ()) -> str | None:
    """One line for an operating-system error the user can act on (a full disk, a read-only
    folder, a permission, a file name that is not UTF-8), naming the path; None for anything
    else (a bug keeps its traceback).

    ``outputs`` are the paths the command writes, named when the error does not carry its own
    (``write()`` on an open file reports ENOSPC without a file name).
    """
    import errno as errno_names

    if isinstance(exc, UnicodeEncodeError) and exc.reason == "surrogates not allowed":
        # Python keeps a file name's undecodable bytes as surrogates; text that must be UTF-8
        # (a database, JSON, a terminal) cannot hold them.
        where = exc.object[max(0, exc.start - 60) : exc.end + 60] if isinstance(exc.object, str) else ""
        return f"a file name that is not valid UTF-8 ({ascii(where)}) cannot be written here; " "rename the file"
    if isinstance(exc, OSError) and exc.errno is not None:
        name = errno_names.errorcode.get(exc.errno)
        if name not in _ENVIRONMENT_ERRNOS:
            return None
        reason = _ENVIRONMENT_ERRNOS[name]
        paths = [p for p in (exc.filename, exc.filename2) if p is not None]
        named = [_path_text(p) for p in outputs if p]
        if paths:
            where = " -> ".join(_path_text(p) for p in paths)
            inside = any(where == o or where.startswith(o.rstrip("/") + "/") for o in named)
            if name in _WRITE_ERRNO_NAMES and named and not inside:
                where += f" (writing {', '.join(named)})"  # e.g. a spool or log file inside the output
        elif name not in _WRITE_ERRNO_NAMES | {"EIO"}:
            return None  # no path to name and not a write's failure: more likely a bug than the user's file
        else:
            where = f"writing {', '.join(named)}" if named else "writing the output"
        return f"{where}: {reason}"
    if type(exc).__name__ == "SafetensorError" and "os error" in str(exc):
        # safetensors reports an I/O failure as its own error type with the OS message inside
        named = [_path_text(p) for p in outputs if p]
        return f"{', '.join(named) or 'output'}: cannot write it ({exc})"
    return None


def _path_text(path) -> str:
    if isinstance(path, bytes):
        return repr(path)  # b'...': the bytes, readable whatever they are
    text = str(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return repr(text.encode("utf-8", "surrogateescape"))
    return text


class NotAvailableError(FdnetError):
    """A method that cannot run here without something the user must supply (e.g. weights)."""
