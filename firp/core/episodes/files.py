"""Crash-safe files: temp names in the same directory, fsync, ``os.replace``; stale temps of dead writers."""

from __future__ import annotations

import os
import re
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from firp.core.episodes.layout import TMP_RE


@contextmanager
def atomic_file(final: Path) -> Iterator[Path]:
    """Yield a temp path beside ``final`` to write; on success it is fsynced and renamed to ``final``
    (and the directory fsynced), on any exception removed: ``final`` is always old-and-whole or
    new-and-whole, never half-written."""
    tmp = temp_path_for(final)
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(final.parent)


def temp_path_for(final: Path) -> Path:
    return final.with_name(f".{final.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def fsync_path(path: Path) -> None:
    """Flush a file's (or directory's) data to disk so an ``os.replace`` publishes whole bytes."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:  # some filesystems refuse fsync on directories; the file fsync matters most
        if not path.is_dir():
            raise
    finally:
        os.close(fd)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:
        return False
    return True


def remove_stale_temps(directory: Path, final_name_re: re.Pattern[str] | None = None) -> list[Path]:
    """Delete temp files whose writer process is gone; keep those a live writer still owns."""
    removed: list[Path] = []
    if not directory.is_dir():
        return removed
    for entry in directory.iterdir():
        match = TMP_RE.match(entry.name)
        if match is None or (final_name_re is not None and not final_name_re.match(match.group("final"))):
            continue
        if pid_alive(int(match.group("pid"))):
            continue
        entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed


