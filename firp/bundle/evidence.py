"""``firp certify``: give a bundle its decision evidence, measured again on its own validation episodes.

A study's export writes the evidence (:func:`firp.core.decisions.decision_evidence`) into every new
bundle's manifest. A bundle exported before that, or one whose evidence should be checked, is certified
from its training dataset: the validation episodes are the ones the export chose its threshold on
(``extra.validation_split`` in the manifest, else the study's split of the dataset), every member scores
them through the inference path, and the ensemble's balanced accuracy at the bundle's threshold must come
out as the manifest says (else the dataset is not the bundle's: refused). Only ``manifest.json`` is
rewritten (atomically); the weights and their hashes stay, so the bundle's version changes and says so.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from firp.bundle.export import write_manifest
from firp.bundle.load import load_bundle
from firp.bundle.types import BundleError
from firp.core.bundle_format import MANIFEST_NAME
from firp.core.cli_types import int_in_range
from firp.core.decisions import EVIDENCE_KEY, decision_evidence

__all__ = ["certify_bundle", "main"]

#: how far the recomputed balanced accuracy may lie from the manifest's (float noise on a borderline score)
AGREEMENT = 0.01


def _validation_index(manifest: dict, names: list[str], labels: np.ndarray) -> np.ndarray:
    split = (manifest.get("extra") or {}).get("validation_split")
    if split and split.get("episodes"):
        position = {name: i for i, name in enumerate(names)}
        missing = [n for n in split["episodes"] if n not in position]
        if missing:
            raise ValueError(f"the dataset lacks {len(missing)} of the bundle's validation episodes "
                             f"(first: {missing[0]}); certify with the bundle's training dataset")
        return np.array([position[n] for n in split["episodes"]])
    from firp.tune import tuning_split  # the split every study's export used

    return tuning_split(labels)[1]


def certify_bundle(bundle_dir: str | os.PathLike, dataset: str | os.PathLike, *, resamples: int = 2000,
                   progress: bool = True, allow_other_data: bool = False) -> dict:
    """Measure the bundle's decision evidence on its validation episodes and write it into its manifest;
    returns the evidence. Raises ValueError naming what does not match.

    The episodes are scored through the serving path (:class:`firp.serving.EnsembleScorer`: the initial
    frame through the bundle's backbone, the plan through every member), so the evidence is about what the
    service computes; that it reproduces the export's balanced accuracy checks both paths agree.

    ``allow_other_data`` accepts a dataset whose content hash is not the training data's (a re-collection
    with the same seeds whose attributes changed, say): the balanced accuracy must still reproduce."""
    from tqdm import tqdm

    from firp.core.episodes import EpisodeDataset
    from firp.serving.scorer import EnsembleScorer

    bundle = load_bundle(bundle_dir)
    manifest = bundle.manifest
    with EpisodeDataset(dataset) as ds:
        content = ds.content_hash()
        trained_on = (manifest.get("training_data") or {}).get("sha256")
        if trained_on and trained_on != content and not allow_other_data:
            raise ValueError(f"--data {dataset}: content hash {content[:12]} is not the bundle's training data "
                             f"({trained_on[:12]}); certify with the dataset the bundle was trained on (or --allow-other-data for a re-collection)")
        names = ds.demo_names
        index = _validation_index(manifest, names, ds.success_labels().astype(bool))
        scorer = EnsembleScorer(bundle)
        labels, scores = [], []
        for i in tqdm(index.tolist(), desc="validation episodes", unit="ep", disable=not progress):
            result = scorer.score(ds.frames(names[i])[0], ds.actions(names[i])[None])
            scores.append(float(result.probabilities[0]))
            labels.append(ds.success(names[i]))
    evidence = decision_evidence(np.array(labels), np.array(scores), bundle.threshold, resamples=resamples)
    evidence["dataset"] = {"path": os.fspath(dataset), "sha256": content,
                           "is_training_data": trained_on is None or trained_on == content}
    recorded = (manifest.get("validation") or {}).get("valid_balanced_accuracy_at_threshold")
    if recorded is not None and abs(recorded - evidence["balanced_accuracy"]) > AGREEMENT:
        raise ValueError(f"the ensemble's balanced accuracy at the threshold on these episodes is "
                         f"{evidence['balanced_accuracy']:.4f}, the manifest says {recorded:.4f}: these are not the "
                         "episodes the bundle was validated on")
    write_manifest(bundle.path / MANIFEST_NAME, {**manifest, EVIDENCE_KEY: evidence})
    load_bundle(bundle.path)  # the rewritten bundle still verifies
    return evidence


def describe(evidence: dict) -> str:
    low, high = evidence["interval"]
    verdict = "informative" if evidence["informative"] else "UNINFORMATIVE (the interval reaches 0.5)"
    return (f"balanced accuracy {evidence['balanced_accuracy']:.3f}, {100 * evidence['level']:.0f}% interval "
            f"[{low:.3f}, {high:.3f}] over {evidence['n_successes']} successes / {evidence['n_failures']} failures: "
            f"{verdict}")


def main(argv: list[str] | None = None, prog: str = "firp certify") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("--bundle", type=Path, required=True, help="the bundle directory (its manifest is rewritten)")
    parser.add_argument("--data", type=Path, required=True, help="the HDF5 dataset the bundle was trained on")
    parser.add_argument("--resamples", type=int_in_range("--resamples", 100, 1_000_000), default=2000)
    parser.add_argument("--allow-other-data", action="store_true",
                        help="accept a dataset whose content hash is not the bundle's training data's (the validation "
                             "episodes are taken by name and the balanced accuracy must still reproduce)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        evidence = certify_bundle(args.bundle, args.data, resamples=args.resamples, progress=not args.no_progress,
                                  allow_other_data=args.allow_other_data)
    except (BundleError, ValueError, FileNotFoundError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    print(f"{args.bundle}: {describe(evidence)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
