"""The model's settings (`ModelConfig`): the paper's parts (C.F., K.R., the decomposition's τ), the
deformation field's size and the product's additions, each with why it is set as it is."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

from ..schema import check_choices, from_fields, json_object
from .kinematics import Basis

Velocity = Literal["paper", "physical"]
KRForm = Literal["convolve", "paper"]
KRInputs = Literal["canonical", "predicted"]
SpawnedMotion = Literal["own", "field"]


@dataclass
class ModelConfig:
    sh_degree: int = 1
    feature_dim: int = 16  # per-Gaussian feature f_i of the fine residual
    knn: int = 8  # dynamic neighbours averaged by the coarse deformation
    # ... within this many times the median distance of a dynamic Gaussian to its knn-th
    # neighbour: one whose nearest dynamic neighbours are further away (a few dynamic Gaussians
    # on a wall, far from the moving object) averages its own offsets instead of borrowing an
    # unrelated object's motion. 0: no bound.
    knn_radius: float = 3.0
    tau: float = 2e-5  # dynamic when the temporal variance K of dx exceeds tau
    K_times: int = 16  # T, times at which K is evaluated
    coarse_to_fine: bool = True  # C.F.
    # After the decomposition, each dynamic Gaussian the field moves gets an opacity that varies in
    # time (`TimeOpacity`, from its fine-residual feature), so the loss can fade it at the
    # times the field puts it wrong. Off in the paper; fit_to_scene turns it on for video
    # ingests (docs/real-footage.md, "Opacity that varies in time").
    time_opacity: bool = False
    kinematic: bool = True  # K.R.
    velocity: Velocity = "physical"
    # False: the physical velocity's two extra field samples are taken without gradients, so
    # the blur's sweep does not train the field (its positions still do); saves their backward.
    velocity_grad: bool = True
    basis: Basis = "paper"  # kinematic frame: paper (e_x reference, switch at 0.99), duff, principal
    # K.R. form: "convolve" (sigma + (|v| dt e)^2 / 12 u u^T on the D3DGS-style residual
    # covariance) or "paper" (eqs. 9-14: projection onto the kinematic frame, sigma_z + eta |v| dt e).
    # convolve is the default because it measured better on every scene (docs/method.md).
    kr_form: KRForm = "convolve"
    # The paper form's inputs: "predicted", the paper's (Σ the covariance the field predicts,
    # R(q) exp(δr) and s exp(λ_s δs), r_z that prediction's axis of largest scale, with its
    # gradient); "canonical", Σ the canonical covariance and r_z its axis, detached, so that δr
    # and δs act once (docs/method.md, "The paper preset").
    kr_inputs: KRInputs = "canonical"
    lambda_s: float = 0.1
    still_len: float = 1e-3  # per-frame motion below which the kinematic frame fades out (0: never)
    kappa_init: float = -2.0  # sigmoid(-2) = 0.12: the lower bound of eta
    deform_spatial: int = 64
    deform_temporal: int = 25
    deform_features: int = 32
    deform_multires: tuple = (1, 2)
    deform_width: int = 64
    deform_depth: int = 1
    bound: float = 1.5  # K-Planes domain, normalised scene units
    # How the Gaussians present for part of the clip (spawned in training, train/spawn.py)
    # move: "own", along their own straight line through their frame (`own_velocity`, lifted
    # from the optical flow at their pixel), the field not moving them; "field", with the
    # field's offsets like any dynamic Gaussian, without training it. "own" fits the frames
    # they are made for and their neighbours (docs/real-footage.md, "Spawned Gaussians that
    # move on their own").
    spawned_motion: SpawnedMotion = "own"

    def __post_init__(self):
        check_choices(self, "model.")
        if not self.knn_radius >= 0:
            raise ValueError(f"model.knn_radius must be >= 0 (0: no bound), got {self.knn_radius!r}")

    def to_dict(self) -> dict:
        from ..migrations import CONFIG_VERSION

        d = asdict(self)
        d["deform_multires"] = list(self.deform_multires)
        return {"config_version": CONFIG_VERSION, **d}

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """From `to_dict`'s output (a run.json's `config.model`); ValueError naming a bad field."""
        from ..migrations import migrate_model_config

        d = migrate_model_config(json_object(d, "model"))
        if "deform_multires" in d:
            d["deform_multires"] = tuple(d["deform_multires"])
        return from_fields(cls, d, "model.")
