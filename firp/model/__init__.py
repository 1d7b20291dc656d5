"""The FIRP model (torch): configs, image encoder, RSSM, success head, FIRP and the baselines.

Imports torch; the numpy-only parts of the method are :mod:`firp.core.contract` and :mod:`firp.core.episodes`.
Losses are pure functions in :mod:`firp.losses`.
"""

from firp.model.baselines import MODEL_KINDS, AMLP, AMLPImage, GRUBaseline, Oracle, build_model, plan_vector
from firp.model.config import (
    BaselineConfig,
    EncoderConfig,
    FIRPConfig,
    HeadConfig,
    LossConfig,
    PlanEventsConfig,
    RSSMConfig,
)
from firp.model.encoder import (
    EfficientNetLite0Backbone,
    FeatureProjection,
    ImageEncoder,
    SmallCNN,
    build_backbone,
    efficientnet_lite0_weights_path,
)
from firp.model.firp import FIRP, Score, first_step
from firp.model.head import SuccessHead
from firp.model.kinematics import ChainFK
from firp.model.ops import plan_categories
from firp.model.plan_events import PlanEvents
from firp.model.rssm import RSSM, sample_overshooting_distances

__all__ = [
    "AMLP",
    "AMLPImage",
    "BaselineConfig",
    "ChainFK",
    "EfficientNetLite0Backbone",
    "EncoderConfig",
    "FIRP",
    "FIRPConfig",
    "FeatureProjection",
    "GRUBaseline",
    "HeadConfig",
    "ImageEncoder",
    "LossConfig",
    "MODEL_KINDS",
    "Oracle",
    "PlanEvents",
    "PlanEventsConfig",
    "RSSM",
    "RSSMConfig",
    "Score",
    "SmallCNN",
    "SuccessHead",
    "build_backbone",
    "build_model",
    "efficientnet_lite0_weights_path",
    "first_step",
    "plan_categories",
    "plan_vector",
    "sample_overshooting_distances",
]
