"""Named recipes: the model, the training loop and the tuning space of a run, in one place.

``firp tune`` and ``firp evaluate`` start from a preset (``--preset``, default ``product``) and each
flag given on the command line overrides one field of it; the bundle a study exports records the
preset and the overrides. Three presets:

* ``paper`` -- the paper's defaults, exactly the dataclass defaults (``FIRPConfig()``,
  ``TrainConfig()``): one plan step per RSSM transition, PlaNet's sizes, L = 20, 224 px images, the
  paper's Optuna grid.
* ``product`` -- what ships (``models/stacking``): eight plan steps per transition, a 128-wide RSSM, a
  sharp attention head (L = 0.05), the plan's grasp-frame description, the frames' own 84 px, 80
  epochs with early stopping after 40 (patience 20), and the narrowed product grid. Why each value:
  ``docs/method.md``. The shipped replacement bundle is ``product`` with four plan steps per
  transition, without the description and with 100 / 50 / 25 epochs (``--action-chunk 4
  --no-plan-geometry --epochs 100 --min-epochs 50 --patience 25``).
* ``generic`` -- ``product`` with the plan's events (:mod:`firp.model.plan_events`: the hand's poses at the
  plan's events by the dataset's own kinematics, read by a relation network) in place of the hand-built
  description: no object size, table height or gripper dimension anywhere, so a new task needs a dataset
  and ``firp tune``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from firp.model.config import EncoderConfig, FIRPConfig, GeometryConfig, HeadConfig, PlanEventsConfig, RSSMConfig
from firp.train import TrainConfig

__all__ = ["PRESETS", "Preset", "preset"]


@dataclass(frozen=True)
class Preset:
    name: str
    summary: str
    train: TrainConfig  # the training loop, with the model (and its loss weights) inside
    space: str  # the Optuna search space (firp.tune.SPACES)

    def with_overrides(self, **overrides: Any) -> TrainConfig:
        """The preset's training config with fields replaced; model fields are given by their flag names:
        ``image_size``, ``action_chunk``, ``deter_dim``, ``hidden``, ``head_temperature``, ``plan_geometry``,
        ``plan_description``, ``description_layers``, ``overshooting``, ``prediction`` and ``description_weight``
        (loss weights). ``None`` values leave the preset's."""
        given = {k: v for k, v in overrides.items() if v is not None}
        model = self.train.model
        if "image_size" in given:
            model = replace(model, encoder=replace(model.encoder, image_size=given.pop("image_size")))
        if "action_chunk" in given:
            model = replace(model, action_chunk=given.pop("action_chunk"))
        rssm = {k: given.pop(f) for k, f in (("deter_dim", "deter_dim"), ("hidden", "hidden")) if f in given}
        if rssm:
            model = replace(model, rssm=replace(model.rssm, **rssm))
        if "head_temperature" in given:
            model = replace(model, head=replace(model.head, temperature=given.pop("head_temperature")))
        geometry = {k: given.pop(f) for k, f in (("enabled", "plan_geometry"), ("description", "plan_description"),
                                                  ("layers", "description_layers"))
                    if f in given}
        if geometry:
            model = replace(model, geometry=replace(model.geometry, **geometry))
            if "description" in geometry and not model.geometry.enabled:
                raise ValueError("--plan-description: the recipe leaves the plan's description out "
                                 "(--no-plan-geometry); drop one of the two")
        events = {k: given.pop(f) for k, f in (("enabled", "plan_events"), ("view", "plan_view")) if f in given}
        if events:
            if events.get("enabled") and model.geometry.enabled:
                if geometry.get("enabled"):
                    raise ValueError("--plan-events: a model reads the hand-built description (--plan-geometry) or "
                                     "the plan's events, not both; drop one of the two")
                model = replace(model, geometry=replace(model.geometry, enabled=False))  # the events replace it
            model = replace(model, events=replace(model.events, **events))
            if model.events.view and not model.events.enabled:
                raise ValueError("--plan-view: the view is read at the plan's events, which the recipe leaves out "
                                 "(--no-plan-events)")
        loss = {k: given.pop(k) for k in ("overshooting", "prediction") if k in given}
        if "description_weight" in given:
            loss["description"] = given.pop("description_weight")
            if loss["description"] > 0 and not model.geometry.enabled:
                raise ValueError("--description-weight: the recipe leaves the plan's description out "
                                 "(--no-plan-geometry); drop one of the two")
        if loss:
            model = replace(model, loss=replace(model.loss, **loss))
        return replace(self.train, model=model, **given)


PAPER = Preset("paper", "the paper's defaults (FIRPConfig(), TrainConfig()) and its Optuna grid", TrainConfig(),
               "paper")

PRODUCT = Preset(
    "product", "what ships: chunk 8, RSSM 128, L 0.05, the plan's grasp-frame description, 84 px, 80/40/20 epochs",
    TrainConfig(epochs=80, min_epochs=40, patience=20,
                model=FIRPConfig(encoder=EncoderConfig(image_size=84), action_chunk=8,
                                 rssm=RSSMConfig(deter_dim=128, hidden=128), head=HeadConfig(temperature=0.05),
                                 geometry=GeometryConfig(enabled=True))),
    "product")

GENERIC = Preset(
    "generic", "product with the plan's events read through the dataset's kinematics (no task's sizes) instead of "
               "the hand-built description",
    replace(PRODUCT.train, model=replace(PRODUCT.train.model, geometry=GeometryConfig(enabled=False),
                                         events=PlanEventsConfig(enabled=True))),
    "product")

PRESETS: dict[str, Preset] = {p.name: p for p in (PAPER, PRODUCT, GENERIC)}


def preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"preset: {name!r} is none of {sorted(PRESETS)}")
    return PRESETS[name]
