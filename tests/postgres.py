"""A real PostgreSQL server for the tests, from Debian's package: ``initdb`` into a temporary
directory, ``pg_ctl start`` listening on a Unix socket in that directory, a database for the test,
and ``pg_ctl stop`` afterwards. No mock: the tuning tests run Optuna's RDB storage against the server a team runs.

PostgreSQL refuses to run as root, so as root (CI) the server runs as the package's ``postgres``
user (``runuser``) in a directory handed to it. Without the binaries (a machine without the
package) :func:`postgres_binaries` is None and the tests that need a server are skipped with the
reason; ``make system-deps`` installs the package.
"""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["postgres_binaries", "postgres_server"]


def postgres_binaries() -> Path | None:
    """The folder with initdb, pg_ctl and createdb (Debian keeps them outside PATH), or None."""
    found = shutil.which("initdb")
    if found and (Path(found).resolve().parent / "createdb").is_file():
        return Path(found).resolve().parent
    versions = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"), key=lambda p: int(p.parts[-3]))
    return versions[-1].parent if versions else None


@contextmanager
def postgres_server(database: str = "firp") -> Iterator[str]:
    """Start a server in a new temporary directory; yield a URL of a fresh ``database``; stop it and
    remove the directory. (Not under pytest's tmp_path: its parents are private to root, and the
    server's user must reach its data directory.)"""
    bin_dir = postgres_binaries()
    if bin_dir is None:
        raise RuntimeError("PostgreSQL's initdb/pg_ctl are not installed (Debian: apt-get install postgresql)")
    as_user: list[str] = []
    if os.geteuid() == 0:
        user = pwd.getpwnam("postgres")
        as_user = ["runuser", "-u", "postgres", "--"]
    root = Path(tempfile.mkdtemp(prefix="firp-postgres-"))
    data, sockets, log = root / "data", root / "sockets", root / "server.log"
    sockets.mkdir(exist_ok=True)
    if as_user:
        for path in (root, sockets):
            os.chown(path, user.pw_uid, user.pw_gid)
        root.chmod(0o755)
    run = lambda *cmd: subprocess.run([*as_user, *cmd], check=True, capture_output=True, text=True, timeout=120)  # noqa: E731
    run(str(bin_dir / "initdb"), "-D", str(data), "-U", "firp", "--auth=trust", "-E", "UTF8", "--no-instructions")
    # A Unix socket in the server's own folder, no TCP port: nothing else can take it or reach it.
    options = f"-k {sockets} -c listen_addresses='' -c fsync=off"
    try:
        run(str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(log), "-o", options, "-w", "-t", "60", "start")
    except subprocess.CalledProcessError as error:
        raise RuntimeError(f"pg_ctl start failed: {error.stderr}\n{log.read_text() if log.exists() else ''}") from error
    try:
        run(str(bin_dir / "createdb"), "-h", str(sockets), "-U", "firp", database)
        yield f"postgresql://firp@/{database}?host={sockets}"
    finally:
        run(str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "-t", "60", "stop")
        shutil.rmtree(root, ignore_errors=True)
