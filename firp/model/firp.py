"""FIRP: feature projection + RSSM + success head.

Training reads cached backbone features of *all* executed frames (``forward_train``); inference
reads the features of the initial image only (``score``). Index convention: see
:mod:`firp.model.rssm` (0-based; index k = frames[k] = paper's t = k + 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from firp.model.config import FIRPConfig
from firp.model.encoder import FeatureProjection, ImageEncoder
from firp.model.head import SuccessHead
from firp.model.normalize import ActionNormalizer
from firp.model.ops import plan_categories
from firp.model.plan_events import build_plan_reader, read_plan
from firp.model.rssm import RSSM

__all__ = ["FIRP", "Score", "chunk_actions", "chunk_frame_index", "first_step", "spread_chunk_weights"]


class Score(NamedTuple):
    """What a model returns at inference."""

    logits: Tensor  # (B,) success logit; sigmoid -> probability
    weights: Tensor | None  # (B, T) attention over time (sums to 1 over valid steps); None: no attention
    features: Tensor | None  # (B, T, E) the sequence the head read: [e_1, e^_2, ..., e^_T]


def chunk_frame_index(T: int, k: int) -> list[int]:
    """Frame observed by each of the ``ceil(T / k)`` chunks: the initial frame for the first chunk,
    then the last frame of each chunk (clamped to ``T - 1`` for a padded last chunk)."""
    n = -(-T // k)
    return [0] + [min((j + 1) * k - 1, T - 1) for j in range(1, n)]


def chunk_actions(actions: Tensor, k: int) -> Tensor:
    """``(B, T, A)`` -> ``(B, ceil(T / k), k * A)``; a short last chunk repeats the last row (a hold)."""
    if k == 1:
        return actions
    B, T, A = actions.shape
    pad = (-T) % k
    if pad:
        actions = torch.cat([actions, actions[:, -1:].expand(B, pad, A)], dim=1)
    return actions.reshape(B, (T + pad) // k, k * A)


def spread_chunk_weights(weights: Tensor, T: int, k: int) -> Tensor:
    """Chunk attention ``(B, Tc)`` -> per plan step ``(B, T)``, each chunk's weight on its frame step."""
    if k == 1:
        return weights
    index = torch.tensor(chunk_frame_index(T, k), device=weights.device)
    return weights.new_zeros(weights.shape[0], T).index_add(1, index, weights)


def first_step(features: Tensor) -> Tensor:
    """``(B, Db)`` stays, ``(B, T, Db)`` -> ``(B, Db)`` of frame 0: inference may only see I_1."""
    if features.ndim == 3:
        return features[:, 0]
    if features.ndim != 2:
        raise ValueError(f"features must be (B, D) or (B, T, D), got shape {tuple(features.shape)}")
    return features


class FIRP(nn.Module):
    """The paper's model. ``cfg.encoder`` sizes the projection; the backbone lives outside (cache)."""

    #: Inference needs only the initial image (the Oracle baseline sets this True).
    requires_future_frames = False

    def __init__(self, cfg: FIRPConfig = FIRPConfig()):
        super().__init__()
        self.cfg = cfg
        E = cfg.encoder.feature_dim
        self.projection = FeatureProjection(cfg.encoder)
        self.rssm = RSSM(cfg.rssm, E, cfg.action_dim * cfg.action_chunk)
        # what the plan says about the scene beside the pooled sequence: the hand-built description or the learned
        # events (off: the paper's head)
        self.geometry = build_plan_reader(cfg)
        self.head = SuccessHead.with_plan_reader(cfg, E, self.geometry)
        self.action_norm = ActionNormalizer(cfg.action_dim)

    def image_encoder(self) -> ImageEncoder:
        """An :class:`ImageEncoder` (builds/loads the backbone) sharing this model's projection."""
        return ImageEncoder(self.cfg.encoder, projection=self.projection)

    def forward_train(
        self,
        features: Tensor,
        actions: Tensor,
        mask: Tensor | None = None,
        overshooting_distances: Sequence[int] = (),
        sample: bool = True,
        overshooting_stride: int = 1,
    ) -> dict[str, object]:
        """Everything the losses need, from cached features of the executed frames.

        ``features`` (B, T, Db) backbone features of frames 0..T-1, ``actions`` (B, T, A),
        ``mask`` (B, T) bool, valid steps a prefix of each row. Returns:

        * ``e`` (B, T, E) projected real features (the head's L_ce and TCR act on them);
        * ``e_target`` (B, T, E) what the RSSM observes and is asked to predict: ``e`` detached
          when ``cfg.loss.stop_target_gradient`` (default), else ``e`` itself;
        * the :meth:`RSSM.observe` tensors, (B, T, .): ``h``, ``post_*``, ``prior_*`` (tau = 1),
          ``feat_prior``, ``feat_post``;
        * ``open_loop``: the :meth:`RSSM.imagine` dict (B, T-1, .) from the filtered latent at
          index 0 under ``actions[:, 1:]`` -- the rollout inference runs (with samples here);
        * ``overshoot``: ``{tau: dict}`` from :meth:`RSSM.overshoot` for the requested distances
          (every ``overshooting_stride``-th start; ``targets`` holds the target indices); the open
          loop above is always there in addition;
        * ``logits``, ``weights``: the head on the real features (the paper's L_ce);
        * ``logits_open_loop``, ``weights_open_loop``, ``features_open_loop`` (B, T, E): the head on
          [e_1, e^_2..e^_T] from the open loop, i.e. what ``score`` computes (up to sampling).
        """
        k = self.cfg.action_chunk
        categories = plan_categories(actions)  # (B, T)
        context = read_plan(self.geometry, actions, mask)  # (B, G) or None, from the raw plan
        if k > 1:  # one transition per chunk of k plan steps; observe each chunk's frame
            index = torch.tensor(chunk_frame_index(actions.shape[1], k), device=features.device)
            features, categories = features[:, index], categories[:, index]  # (B, Tc, Db), (B, Tc)
            mask = mask[:, index] if mask is not None else None
        e = self.projection(features)  # (B, T, E) (T = Tc when chunked)
        # what the RSSM observes and predicts: e itself, or e without a gradient into the projection
        e_target = e.detach() if self.cfg.loss.stop_target_gradient else e  # (B, T, E)
        actions = chunk_actions(self.action_norm(actions), k)  # (B, Tc, k * A); one-hot columns unchanged
        obs = self.rssm.observe(e_target, actions, sample=sample)
        # the open loop is what inference classifies: rolled on means when cfg.loss.open_loop_sample is off
        ol_sample = sample and self.cfg.loss.open_loop_sample
        s_start = obs["post_sample" if ol_sample else "post_mean"][:, 0]  # (B, S)
        open_loop = self.rssm.imagine(obs["h"][:, 0], s_start, actions[:, 1:], sample=ol_sample)
        seq_ol = torch.cat([e[:, :1], open_loop["feat"]], dim=1) if actions.shape[1] > 1 else e[:, :1]
        logits, weights = self.head(e, mask, context)
        logits_ol, weights_ol = self.head(seq_ol, mask, context)
        overshoot = {
            int(tau): self.rssm.overshoot(
                obs["h"], obs["post_sample"], actions, int(tau), sample=sample, stride=overshooting_stride
            )
            for tau in overshooting_distances
        }
        return {
            "e": e,
            "e_target": e_target,
            "categories": categories,
            "mask": mask,
            **obs,
            "open_loop": open_loop,
            "overshoot": overshoot,
            "logits": logits,
            "weights": weights,
            "logits_open_loop": logits_ol,
            "weights_open_loop": weights_ol,
            "features_open_loop": seq_ol,
            # the description's own score (the head's logit without the pooled sequence's share)
            **({"logits_description": self.head.description_logit(context)} if context is not None else {}),
        }

    def forward_initial(self, first_features: Tensor, actions: Tensor, mask: Tensor | None = None,
                        sample: bool = True) -> Tensor:
        """Training logits ``(B,)`` of episodes that kept only their initial frame: the open loop of
        :meth:`forward_train` (the classification inference runs), from ``first_features`` (B, Db) alone. As
        there, the RSSM reads ``e_1`` without a gradient into the projection when ``stop_target_gradient``,
        the head reads it with one, and the rollout samples when ``cfg.loss.open_loop_sample``."""
        k, T = self.cfg.action_chunk, actions.shape[1]
        context = read_plan(self.geometry, actions, mask)  # (B, G) or None
        if k > 1 and mask is not None:
            mask = mask[:, torch.tensor(chunk_frame_index(T, k), device=mask.device)]
        e1 = self.projection(first_step(first_features))  # (B, E)
        e1_in = e1.detach() if self.cfg.loss.stop_target_gradient else e1
        roll = self.rssm.rollout_from_first(e1_in, chunk_actions(self.action_norm(actions), k),
                                            sample=sample and self.cfg.loss.open_loop_sample)
        seq = torch.cat([e1.unsqueeze(1), roll["features"][:, 1:]], dim=1)  # (B, Tc, E)
        logits, _ = self.head(seq, mask, context)
        return logits

    def score(
        self, first_features: Tensor, actions: Tensor, mask: Tensor | None = None, sample: bool = False
    ) -> Score:
        """Inference from the initial image only.

        ``first_features`` (B, Db) backbone features of I_1 (a (B, T, Db) tensor is accepted and
        only its frame 0 is read), ``actions`` (B, T, A), ``mask`` (B, T). ``sample=False`` rolls
        the means, so one plan always gets one score.
        """
        k, T = self.cfg.action_chunk, actions.shape[1]
        context = read_plan(self.geometry, actions, mask)  # (B, G) or None
        if k > 1 and mask is not None:
            mask = mask[:, torch.tensor(chunk_frame_index(T, k), device=mask.device)]
        e1 = self.projection(first_step(first_features))  # (B, E)
        roll = self.rssm.rollout_from_first(e1, chunk_actions(self.action_norm(actions), k), sample=sample)
        logits, weights = self.head(roll["features"], mask, context)  # weights (B, Tc)
        return Score(logits, spread_chunk_weights(weights, T, k), roll["features"])
