"""What a bundle holds once loaded, the one error it raises, and the rules export and load share."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torch import Tensor, nn

from firp.core.contract import PlanLimits
from firp.model.config import EncoderConfig, FIRPConfig

__all__ = ["POST_EXECUTION_KINDS", "Bundle", "BundleError", "BundleMember", "backbone_key", "shared_encoder",
           "state_mismatch"]

#: Kinds that need frames *after* execution: they cannot score a plan beforehand.
POST_EXECUTION_KINDS = ("oracle",)


class BundleError(ValueError):
    """A bundle broke a rule. ``path`` is the offending file, ``rule`` the rule's short name:

    ``missing``, ``corrupt``, ``schema``, ``format_version``, ``contract_version``, ``contract``,
    ``sha256``, ``config``, ``state_dict``, ``backbone``.
    """

    def __init__(self, path: str | os.PathLike, rule: str, detail: str):
        self.path = Path(path)
        self.rule = rule
        self.detail = detail
        super().__init__(f"{self.path}: {detail} (rule: {rule})")


@dataclass
class BundleMember:
    """One trained ensemble member as training hands it over."""

    kind: str  # one of firp.model.baselines.MODEL_KINDS (not "oracle")
    config: FIRPConfig
    model: nn.Module
    metrics: dict[str, float] = field(default_factory=dict)  # validation metrics of this member


@dataclass(frozen=True)
class Bundle:
    """A loaded, verified bundle: models in eval mode with gradients off, ready to score."""

    path: Path
    manifest: dict[str, Any]
    kinds: tuple[str, ...]
    configs: tuple[FIRPConfig, ...]
    models: tuple[nn.Module, ...]
    backbone: nn.Module  # the one frozen backbone every member's features come from
    encoder_config: EncoderConfig  # the members' shared encoder settings (backbone, image size)
    threshold: float
    t_range: PlanLimits

    @property
    def name(self) -> str:
        return str(self.manifest["name"])

    @property
    def task(self) -> str:
        return str(self.manifest["task"])


def backbone_key(cfg: EncoderConfig) -> dict[str, Any]:
    """What determines the backbone's output for an image: members must agree on all of it to
    share one backbone (the projection after it may differ freely)."""
    key: dict[str, Any] = {
        "name": cfg.backbone,
        "image_size": cfg.image_size,
        "normalization": cfg.resolved_normalization,
        "dim": cfg.backbone_dim,
    }
    if cfg.backbone == "small_cnn":
        key["small_cnn_channels"] = list(cfg.small_cnn_channels)
    return key


def shared_encoder(configs: Sequence[FIRPConfig], where: str | os.PathLike) -> EncoderConfig:
    """The one encoder setting of all members; a :class:`BundleError` if they cannot share one."""
    for k, c in enumerate(configs):
        if not c.encoder.freeze_backbone:
            raise BundleError(where, "backbone", f"member {k} was configured with an unfrozen (per-member trained) "
                              "backbone: a bundle holds one frozen backbone shared by all members")
    keys = [backbone_key(c.encoder) for c in configs]
    for k, key in enumerate(keys[1:], start=1):
        if key != keys[0]:
            raise BundleError(where, "backbone", f"member {k} uses backbone {key}, member 0 uses {keys[0]}: "
                              "an ensemble shares one backbone and image size")
    return configs[0].encoder


def state_mismatch(module: nn.Module, state: Mapping[str, Tensor]) -> str | None:
    """Every difference between ``state`` and ``module.state_dict()`` by name, or None."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = [
        f"{k}: {tuple(state[k].shape)} {state[k].dtype} != {tuple(expected[k].shape)} {expected[k].dtype}"
        for k in sorted(set(expected) & set(state))
        if state[k].shape != expected[k].shape or state[k].dtype != expected[k].dtype
    ]
    parts = []
    if missing:
        parts.append(f"missing keys {missing}")
    if unexpected:
        parts.append(f"unexpected keys {unexpected}")
    if wrong:
        parts.append(f"wrong shapes/dtypes {wrong}")
    return "; ".join(parts) or None
