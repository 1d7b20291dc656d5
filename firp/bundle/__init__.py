"""Ensemble bundles: the one artefact training hands to the scoring service.

A bundle is a directory::

    <dir>/manifest.json            what the bundle is, and the sha256 of every weights file
    <dir>/member_<k>.safetensors   state dict of ensemble member k (projection + RSSM + head, ...)
    <dir>/backbone.safetensors     the image backbone, unless it is the pinned pretrained
                                   EfficientNet-Lite0 (identified by the sha256 of its weights)

Why this shape:

* **safetensors, never pickle.** A bundle may come from another machine; ``torch.load`` of a
  pickle runs code. Nothing in this module unpickles anything.
* **Everything checked at load, each failure named.** The service must refuse a bundle that is
  missing a file, corrupt, altered after export, made for another plan contract, or whose weights
  do not fit the configured architecture -- at start-up, with a message naming the file and the
  rule (:class:`BundleError`), not with a shape error deep in the first request.
* **The backbone travels with the bundle when it is not pinned.** Members only hold what sits on
  top of the backbone features. A ``small_cnn`` backbone is trained (or randomly initialised), so
  its weights are part of the model: without them another process would compute other features.
* **Atomic export.** Files are written into a temporary sibling directory which is renamed into
  place, so a reader never sees half a bundle.

The sha256 values protect integrity (a flipped byte, a truncated copy), not authenticity: whoever
can rewrite the manifest can rewrite the hashes too.
"""

from firp.bundle.export import export_bundle
from firp.bundle.load import load_bundle
from firp.bundle.types import Bundle, BundleError, BundleMember, backbone_key
from firp.core.bundle_format import BACKBONE_FILE, BUNDLE_FORMAT, BUNDLE_FORMAT_VERSION, MANIFEST_NAME, sha256_file

__all__ = ["BACKBONE_FILE", "BUNDLE_FORMAT", "BUNDLE_FORMAT_VERSION", "MANIFEST_NAME", "Bundle", "BundleError",
           "BundleMember", "backbone_key", "export_bundle", "load_bundle", "sha256_file"]
