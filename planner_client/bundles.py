"""Where the scoring service's bundle for a task is, found without importing torch.

The planner launches the service with a bundle path; it must not import ``firp.bundle`` (torch) to
find or check it, so it only locates the ``firp`` package on disk (``importlib.util.find_spec``
reads no module) and looks for the bundle's manifest. Full verification (checksums, contract) is
the service's job at start-up.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

MANIFEST = "manifest.json"  # firp.bundle.MANIFEST_NAME, repeated here to keep torch out


class MissingBundle(FileNotFoundError):
    """No bundle where the run needs one; the message says how to make one."""


def shipped_bundle_dir(task: str) -> Path:
    """``firp/bundles/<task>`` inside the installed ``firp`` package (wherever the run starts from)."""
    spec = importlib.util.find_spec("firp")
    if spec is None or not spec.submodule_search_locations:
        raise MissingBundle("the firp package is not installed: cannot find its shipped bundles "
                            "(pip install -e . or pass --bundle DIR)")
    return Path(next(iter(spec.submodule_search_locations))) / "bundles" / task


def require_bundle(path: Path, task: str) -> Path:
    """``path`` if it holds a bundle manifest; else :class:`MissingBundle` naming it and the fix."""
    if (path / MANIFEST).is_file():
        return path
    what = "does not exist" if not path.exists() else f"has no {MANIFEST}"
    raise MissingBundle(
        f"no FIRP bundle for task {task!r}: {path} {what}. Make one by tuning on a labelled dataset and "
        f"exporting the best ensemble: python -m firp.tune --data data/{task}.h5 --trials 20 "
        f"--export firp/bundles/{task} (or pass --bundle DIR, --service URL of a running scoring service, "
        "or --no-score to run TAMP alone and the oracle only)")
