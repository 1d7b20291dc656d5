"""Request and response bodies (pydantic v2): the service's public contract, and its OpenAPI schema.

Why the plan is only *typed* here and not fully checked: the contract's rules (width 16, T range,
finiteness, one-hot, joint limits) live in exactly one place, :func:`firp.core.contract.validate_plan`,
which names the rule and the offending ``plan[t][c]``. The JSON schema still *documents* the
T x 16 shape (``minItems``/``maxItems``), so clients and schema-driven tools see it. Numbers are
strict: ``"0.5"`` and ``true`` are not numbers (pydantic would otherwise coerce them).

All request models forbid unknown fields: a misspelt ``"plans"`` in a single-plan request must be
an error, not a silently ignored field.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, Strict

from firp.core.contract import CATEGORIES, JOINT_NAMES, N_CATEGORIES, PLAN_WIDTH, T_MAX, T_MIN

__all__ = [
    "BatchScoreRequest",
    "BatchScoreResponse",
    "ErrorDetail",
    "ErrorResponse",
    "HealthResponse",
    "ModelInfo",
    "DecisionEvidence",
    "EvidenceDataset",
    "ModelRef",
    "PlanResult",
    "ReadyResponse",
    "ScoreRequest",
    "ScoreResponse",
    "V2InferRequest",
    "V2InferResponse",
    "V2Live",
    "V2ModelMetadata",
    "V2ModelReady",
    "V2Ready",
    "V2RequestInput",
    "V2RequestOutput",
    "V2ResponseOutput",
    "V2ServerMetadata",
    "V2TensorMetadata",
]

# ------------------------------------------------------------------------------------------
# The plan
# ------------------------------------------------------------------------------------------

_PLAN_DESCRIPTION = (
    f"The plan in its canonical form: T rows (steps at 4 FPS) of {PLAN_WIDTH} numbers each. Columns "
    f"0-{N_CATEGORIES - 1} are a one-hot action category in this order: {', '.join(CATEGORIES)}; columns "
    f"{N_CATEGORIES}-{PLAN_WIDTH - 1} are the Franka Panda joint targets {', '.join(JOINT_NAMES)} (radians for "
    f"the seven arm joints, metres for the two fingers), inside the Panda's joint limits. The contract allows "
    f"T in [{T_MIN}, {T_MAX}]; a bundle accepts the narrower range it was trained on (GET /v1/model, "
    "contract.t_min/t_max). Checked by firp.core.contract.validate_plan: a violation is a 422 naming "
    "plan[t] or plan[t][c] and the rule (shape, width, length, finite, one_hot, joint_limits)."
)

Number = Annotated[float, Strict()]
PlanRow = Annotated[list[Number], Field(json_schema_extra={"minItems": PLAN_WIDTH, "maxItems": PLAN_WIDTH})]
Plan = Annotated[list[PlanRow], Field(description=_PLAN_DESCRIPTION,
                                      json_schema_extra={"minItems": T_MIN, "maxItems": T_MAX})]

_HOME = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]


def _example_row(category: str, fingers: float) -> list[float]:
    row = [0.0] * N_CATEGORIES
    row[CATEGORIES.index(category)] = 1.0
    return row + _HOME + [fingers, fingers]


#: A contract-valid T = 8 plan (the contract's shortest) for the OpenAPI examples.
EXAMPLE_PLAN = [
    _example_row("move_before_grasp", 0.04),
    _example_row("move_before_grasp", 0.04),
    _example_row("grasp", 0.02),
    _example_row("hold", 0.02),
    _example_row("move", 0.02),
    _example_row("hold_before_release", 0.02),
    _example_row("release", 0.04),
    _example_row("move_after_release", 0.04),
]
#: A 16 x 16 PNG, base64 (the example image; real requests send the camera frame).
EXAMPLE_IMAGE = ("iVBORw0KGgoAAAANSUhEUgAAABAAAAAQCAIAAACQkWg2AAAAIElEQVR42mM8YaPBQApgYiARjGogBrBMkjMaDaWB1wAAJR8CMIy+"
                 "4x8AAAAASUVORK5CYII=")

_IMAGE_DESCRIPTION = (
    "The scene before execution: a PNG or JPEG file, standard base64 (with padding). Any size within the "
    "service's limits (sides 16-4096 px by default, aspect ratio <= 4) is accepted and resized to the bundle's "
    "image size (GET /v1/model, image.size) exactly as training frames were (bilinear, antialiased; a "
    "non-square image is stretched). Grey, palette and alpha images are converted to RGB."
)
_TASK_DESCRIPTION = "Optional task name; if given it must equal the bundle's task (else 422, field 'task')."
_REQUEST_ID_DESCRIPTION = "Optional client id, echoed in the response."
_FAILURE_STEP_DESCRIPTION = (
    "Only when success is false: the step (0-based) with the largest attention weight, averaged over the "
    "members, i.e. the step of the predicted future the failure prediction rests on most. null when the plan "
    "is predicted to succeed or no member has attention."
)


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ScoreRequest(_Request):
    """POST /v1/score: one image, one plan."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"image": EXAMPLE_IMAGE, "plan": EXAMPLE_PLAN, "task": "stacking", "request_id": "trial-7-order-2"},
    ]})

    image: str = Field(description=_IMAGE_DESCRIPTION)
    plan: Plan
    task: str | None = Field(None, max_length=64, description=_TASK_DESCRIPTION)
    request_id: str | None = Field(None, max_length=128, description=_REQUEST_ID_DESCRIPTION)


class BatchScoreRequest(_Request):
    """POST /v1/score/batch: one image, N candidate plans, scored in one call."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"image": EXAMPLE_IMAGE, "plans": [EXAMPLE_PLAN, EXAMPLE_PLAN], "request_id": "trial-7"},
    ]})

    image: str = Field(description=_IMAGE_DESCRIPTION)
    plans: list[Plan] = Field(
        description="N candidate plans (1 <= N <= the service's max_batch, 64 by default), each in the canonical "
                    "form described for /v1/score. Plans of equal T run through the members as one batch.",
        json_schema_extra={"minItems": 1},
    )
    task: str | None = Field(None, max_length=64, description=_TASK_DESCRIPTION)
    request_id: str | None = Field(None, max_length=128, description=_REQUEST_ID_DESCRIPTION)


class ModelRef(BaseModel):
    name: str = Field(description="bundle name (manifest 'name')")
    version: str = Field(description="manifest 'version' (or extra.version) if set, else the first 12 hex digits "
                                     "of the manifest's sha256, which covers every weights file")


class PlanResult(BaseModel):
    score: float = Field(ge=0.0, le=1.0, description="success probability: mean over the members")
    success: bool = Field(description="score >= threshold")
    member_scores: list[float] = Field(description="each member's success probability, in bundle order")
    spread: float = Field(ge=0.0, description="standard deviation of member_scores (population, ddof 0): the "
                                              "ensemble's disagreement, a measure of uncertainty")
    failure_step: int | None = Field(description=_FAILURE_STEP_DESCRIPTION)


class ScoreResponse(PlanResult):
    threshold: float = Field(description="the bundle's decision threshold (chosen on validation data)")
    attention: list[float] | None = Field(
        description="per step, the members' mean attention weight (sums to 1); null if no member has attention")
    model: ModelRef
    request_id: str | None
    elapsed_ms: float = Field(description="time spent in the service on this request")


class BatchScoreResponse(BaseModel):
    results: list[PlanResult] = Field(description="one result per plan, in request order")
    threshold: float
    model: ModelRef
    request_id: str | None
    elapsed_ms: float


class ErrorDetail(BaseModel):
    field: str | None = Field(description="the offending part of the request, e.g. 'plan[3][7]', 'image', 'task'; "
                                          "null if no single part is to blame")
    rule: str = Field(description="short stable name of the rule broken, e.g. one_hot, joint_limits, length, "
                                  "dimensions, base64, media_type, max_body_bytes, not_ready, api_key")
    message: str


class ErrorResponse(BaseModel):
    """Every 4xx/5xx response body."""

    error: ErrorDetail


class V2ErrorResponse(BaseModel):
    """Every 4xx/5xx body on the V2 routes: the protocol's ``{"error": "<message>"}``, with the field
    and the rule beside it."""

    error: str = Field(description="what is wrong, for humans (the Open Inference Protocol's error string)")
    field: str | None = Field(None, description="the offending part of the request; null if no single part")
    rule: str = Field(description="short stable name of the rule broken (as in the /v1 error shape)")


class HealthResponse(BaseModel):
    status: Literal["alive"] = "alive"


class ReadyResponse(BaseModel):
    status: Literal["ready", "starting", "draining", "unloaded", "stopping"]
    model: ModelRef | None = None
    warmup_ms: float | None = None
    informative: bool | None = Field(None, description="false: the bundle's validation interval reaches 0.5, so "
                                     "clients should not replan on its scores; null: the bundle carries no evidence")


class EvidenceDataset(BaseModel):
    """The dataset a certification scored (``firp certify`` records it; its hash may differ from the training
    data's when the same seeds were collected again)."""

    path: str
    sha256: str
    is_training_data: bool = Field(description="the content hash equals the bundle's training data's (or the bundle names none)")


class DecisionEvidence(BaseModel):
    """What decisions on the scores may rest on (firp.core.decisions; ``firp certify`` writes it)."""

    balanced_accuracy: float = Field(description="the ensemble's validation balanced accuracy at the threshold")
    interval: tuple[float, float] = Field(description="its bootstrap confidence interval")
    level: float
    resamples: int
    method: str
    informative: bool = Field(description="the interval's lower end lies above 0.5")
    n_successes: int
    n_failures: int
    failure_scores: list[float] = Field(description="the validation failures' scores, sorted: a client's conformal "
                                                    "threshold for a false-accept rate alpha comes from them")
    dataset: EvidenceDataset | None = Field(None, description="the dataset `firp certify` measured it on (absent "
                                                             "when the export measured it on its training data)")


class MemberInfo(BaseModel):
    kind: str
    validation: dict[str, float]


class ContractInfo(BaseModel):
    version: str
    plan_width: int
    categories: list[str]
    joint_names: list[str]
    joint_lower: list[float]
    joint_upper: list[float]
    fps: int
    t_min: int = Field(description="shortest plan this bundle accepts")
    t_max: int = Field(description="longest plan this bundle accepts")


class ImageInfo(BaseModel):
    size: int = Field(description="images are resized to size x size before the backbone")
    backbone: str
    normalization: str
    resize: str


class ModelInfo(BaseModel):
    """GET /v1/model: what is loaded, how good it was on validation data, and what it accepts."""

    name: str
    version: str
    task: str
    sha256: str = Field(description="sha256 of the bundle's manifest.json")
    created_utc: str | None
    format_version: int | None
    threshold: float
    members: list[MemberInfo]
    metrics: dict[str, float] = Field(description="the ensemble's validation metrics")
    calibration: dict[str, float]
    training_data: dict[str, str]
    informative: bool | None = Field(description="false: not shown better than chance on validation data (the "
                                     "planner client then executes TAMP's first plan); null: no evidence")
    decision_evidence: DecisionEvidence | None
    contract: ContractInfo
    image: ImageInfo


# ------------------------------------------------------------------------------------------
# Open Inference Protocol (KServe V2), REST/JSON
# ------------------------------------------------------------------------------------------


class V2ServerMetadata(BaseModel):
    name: str
    version: str
    extensions: list[str]


class V2Live(BaseModel):
    live: bool


class V2Ready(BaseModel):
    ready: bool


class V2ModelReady(BaseModel):
    name: str
    ready: bool


class V2TensorMetadata(BaseModel):
    name: str
    datatype: str
    shape: list[int]


class V2ModelMetadata(BaseModel):
    name: str
    versions: list[str]
    platform: str
    inputs: list[V2TensorMetadata]
    outputs: list[V2TensorMetadata]


class V2RequestInput(_Request):
    name: str = Field(description="'image' or 'plan'")
    shape: list[Annotated[int, Strict()]]
    datatype: str = Field(description="image: UINT8 (H x W x 3, or 1 x H x W x 3) or BYTES (shape [1], a base64 "
                                      "PNG/JPEG); plan: FP32 or FP64 (T x 16, or N x T x 16 for N plans)")
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data_size: the tensor's elements are sent as raw bytes (little-endian, row-major) "
                          "after the JSON header instead of in `data` (binary tensor extension; the request then "
                          "carries an Inference-Header-Content-Length header)")
    data: list[Any] | None = Field(None, description="the tensor's elements in row-major order, flat or nested; "
                                                     "omitted when parameters.binary_data_size is given")


class V2RequestOutput(_Request):
    name: str
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data: true returns this output as raw bytes after the JSON header")


class V2InferRequest(_Request):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "id": "trial-7",
        "inputs": [
            {"name": "image", "shape": [1], "datatype": "BYTES", "data": [EXAMPLE_IMAGE]},
            {"name": "plan", "shape": [len(EXAMPLE_PLAN), PLAN_WIDTH], "datatype": "FP32",
             "data": [x for row in EXAMPLE_PLAN for x in row]},
        ],
    }]})

    id: str | None = Field(None, max_length=128)
    model_name: str | None = Field(None, max_length=256, description="sent by some V2 clients (KServe's); if "
                                   "given, it must equal the path's model")
    model_version: str | None = Field(None, max_length=256, description="if given, the model's version")
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data_output: true returns every output not asking otherwise as raw bytes; "
                          "timeout: microseconds (0: none) -- work still queued when it ends is answered 504")
    inputs: list[V2RequestInput] = Field(json_schema_extra={"minItems": 1})
    outputs: list[V2RequestOutput] | None = None


class V2ResponseOutput(BaseModel):
    name: str
    shape: list[int]
    datatype: str
    parameters: dict[str, Any] | None = Field(
        None, description="binary_data_size: the output's bytes follow the JSON header (binary tensor extension)")
    data: list[Any] | None = Field(None, description="row-major elements; omitted for a binary output")


class V2InferResponse(BaseModel):
    model_name: str
    model_version: str
    id: str | None = None
    parameters: dict[str, Any] | None = None
    outputs: list[V2ResponseOutput]
