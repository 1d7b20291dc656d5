"""What a bundle is on disk, and where the shipped ones live -- without torch.

A bundle is the one artefact training hands to the scoring service: a directory with a
``manifest.json`` (what it is, and the sha256 of every weights file) beside safetensors files.
Reading and writing the weights needs torch (:mod:`firp.bundle`); naming its files, hashing them
and finding a task's shipped bundle does not, so the planner, the sim worker and the compose set-up
use this module alone.

The shipped bundles live in the repository's top-level ``models/<task>/`` -- data, not code: they are
not installed into the Python package, and only the scoring service's image carries them. The
setting ``FIRP_MODELS_DIR`` points elsewhere (an installed wheel, a mounted volume).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["BACKBONE_FILE", "bundle_version", "BUNDLE_FORMAT", "BUNDLE_FORMAT_VERSION", "MANIFEST_NAME", "MODELS_DIR_ENV",
           "MissingBundle", "models_dir", "require_bundle", "sha256_file", "shipped_bundle_dir"]

BUNDLE_FORMAT = "firp-ensemble-bundle"
#: Bumped when the layout or the meaning of a manifest field changes; readers accept only equal.
BUNDLE_FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
BACKBONE_FILE = "backbone.safetensors"
#: The environment variable naming the folder of shipped bundles (one sub-folder per task).
MODELS_DIR_ENV = "FIRP_MODELS_DIR"


class MissingBundle(FileNotFoundError):
    """No bundle where one is needed; the message says how to make one."""


def bundle_version(bundle_dir: str | os.PathLike, manifest: dict) -> str:
    """The version a service reports for a bundle: the manifest's own ``version`` (or ``extra.version``)
    if it names one, else the first 12 hex digits of the manifest's sha256 -- which records the sha256 of
    every weights file, so any change to the bundle changes it."""
    extra = manifest.get("extra") or {}
    named = manifest.get("version") or extra.get("version")
    return str(named) if named else sha256_file(Path(bundle_dir) / MANIFEST_NAME)[:12]


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def models_dir() -> Path:
    """The folder of shipped bundles: ``$FIRP_MODELS_DIR``, else ``models/`` beside the ``firp`` sources
    (the repository's, for a checkout or an editable install -- wherever the command is started from)."""
    configured = os.environ.get(MODELS_DIR_ENV)
    if configured:
        return Path(configured)
    import firp  # cheap: the package's __init__ imports nothing

    return Path(firp.__file__).resolve().parents[1] / "models"


def shipped_bundle_dir(task: str) -> Path:
    """The shipped bundle of ``task``: ``models_dir() / task`` (not checked: see :func:`require_bundle`)."""
    return models_dir() / task


def require_bundle(path: Path, task: str) -> Path:
    """``path`` if it holds a bundle manifest; else :class:`MissingBundle` naming it and the fix.

    Only the manifest's presence is checked here; full verification (checksums, contract) is the
    loader's, at the service's start-up."""
    if (path / MANIFEST_NAME).is_file():
        return path
    what = "does not exist" if not path.exists() else f"has no {MANIFEST_NAME}"
    raise MissingBundle(
        f"no FIRP bundle for task {task!r}: {path} {what}. Make one by tuning on a labelled dataset and "
        f"exporting the best ensemble: firp tune --data data/{task}.h5 --trials 20 --export models/{task} "
        f"(or set {MODELS_DIR_ENV}, pass --bundle DIR, --service URL of a running scoring service, or --no-score "
        "to run TAMP alone and the oracle only)")
