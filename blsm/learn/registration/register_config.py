"""Settings of the scan registration (thesis Sec. 5.4.1, Eqs. 5.13-5.25): :class:`RegisterConfig`.

Read by both stages (:mod:`blsm.learn.registration.landmark_fit`, :mod:`blsm.learn.registration.surface_fit`) and by the
driver (:mod:`blsm.learn.registration.register`); ``configs/blsm/register.yaml`` holds the same values.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from blsm.io import read_yaml

DEFAULT_CONFIG = Path(__file__).resolve().parents[3] / "configs" / "blsm" / "register.yaml"


@dataclass
class RegisterConfig:
    """Settings of both stages (YAML keys are the field names; unknown keys are errors).

    Attributes:
        stage1_iterations: L-BFGS iterations of the articulated landmark fit (Eq. 5.13).
        stage1_rigid_iterations: L-BFGS iterations on global orientation/translation only, first.
        angle_prior: weight (m^2 per rad^2) of mean(theta^2), pulling unconstrained angles to 0.
        scale_prior: weight (m^2) of mean(log(b / b_mean)^2), pulling bone scales to the mean.
        symmetry_prior: weight (m^2) of mean((log b_left - log b_right)^2); 0 disables it.
        shape_init: engineering addition (not in the thesis): also fit the initial model's shape
            coefficients (Eq. 8) in stage 1 and in :func:`blsm.learn.registration.surface_fit.fit_surface`;
            stage 2 then starts from ``V_T + V_s`` (the reported V_D includes V_s). False gives the
            thesis' pipeline.
        stage1_shape_iterations: L-BFGS iterations of the landmark fit with shape, after the
            skeleton-only fit.
        shape_prior: weight (m^2) of mean(c_s^2) (coefficients are in standard deviations).
        surface_rounds, surface_iterations: ICP rounds (fresh MNN pairs) and L-BFGS iterations per
            round of :func:`blsm.learn.registration.surface_fit.fit_surface` (engineering addition); 0 skips it.
        iterations: Adam iterations of the free-form refinement (Eq. 5.14).
        lr: Adam learning rate on V_D, metres (thesis: 0.005).
        lr_decay: factor applied to the learning rate on a plateau (thesis: 0.9).
        plateau_patience: iterations without a 0.1 % improvement of the loss before decaying.
        scan_samples: points sampled on the scan surface per refresh (thesis: 50k; 20k here keeps a
            scan at a few seconds on one core).
        model_samples: points sampled on S^ per refresh (thesis: 20k; 8k here, same reason).
        mnn_refresh: iterations between fresh samples and MNN pairs (1 = every iteration).
        lambda_mnn, lambda_lm: data-term weights of Eq. 5.15.
        lambda_smoothness: Eq. 5.21. lambda_ev, lambda_el: Eq. 5.22. lambda_rigid: Eq. 5.25.
            lambda_ev deviates from the thesis (0.003 there, 3.0 here): with metres and mean
            normalisation 0.003 leaves E_EV negligible, vertices slide along the surface and the
            correspondence error grows (measured on an Anny scan: 0.1 -> 8.5 mm, 1 -> 4.8 mm,
            3 -> 4.4 mm, 10 -> 4.5 mm, 30 -> 4.9 mm mean error vs ground truth).
        mnn_tangent_weight: weight in [0, 1] of the part of each MNN residual along the scan
            surface in stage 2 (1 = Eq. 5.15's point-to-point distance, the thesis; 0 = point-to-
            plane, the distance along the scan normal only). Random surface samples are about 1 cm
            apart at 20k samples, so a point-to-point pair also pulls across the surface; measured
            on 18 held-out scans of the default population (``experiments/registration/registration_floor.py``):
            4.23 mm mean error at 1, 4.05 mm at 0. The default stays the thesis' term, with
            which the packaged model was made.
        normalisation: "mean" (every term a mean over its elements, as PyTorch3D's losses) or
            "sum" (sums over elements, divided by the template's vertex count V for readable
            numbers; Adam does not see a common factor).
        seed: random seed of the surface sampling.
    """

    stage1_iterations: int = 300
    stage1_rigid_iterations: int = 20
    angle_prior: float = 1e-6
    scale_prior: float = 1e-5
    symmetry_prior: float = 0.0
    shape_init: bool = True
    stage1_shape_iterations: int = 200
    shape_prior: float = 1e-5
    surface_rounds: int = 6
    surface_iterations: int = 15
    iterations: int = 150
    lr: float = 0.005
    lr_decay: float = 0.9
    plateau_patience: int = 5
    scan_samples: int = 20_000
    model_samples: int = 8_000
    mnn_refresh: int = 5
    lambda_mnn: float = 1.0
    lambda_lm: float = 1.0
    lambda_smoothness: float = 0.007
    lambda_ev: float = 3.0
    lambda_el: float = 0.02
    lambda_rigid: float = 0.01
    normalisation: str = "mean"
    mnn_tangent_weight: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("stage1_iterations", "stage1_rigid_iterations", "stage1_shape_iterations",
                     "iterations", "surface_rounds", "surface_iterations", "mnn_refresh",
                     "scan_samples", "model_samples", "plateau_patience"):
            v = getattr(self, name)
            if v < (1 if name in ("mnn_refresh", "scan_samples", "model_samples", "plateau_patience") else 0):
                raise ValueError(f"{name} must be positive, got {v}")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and (not math.isfinite(v) or v < 0):
                raise ValueError(f"{f.name} must be finite and >= 0, got {v}")
        if self.normalisation not in ("mean", "sum"):
            raise ValueError(f"normalisation must be 'mean' or 'sum', got {self.normalisation!r}")
        if self.mnn_tangent_weight > 1:
            raise ValueError(f"mnn_tangent_weight must be in [0, 1], got {self.mnn_tangent_weight}")
        if not 0 < self.lr_decay <= 1:
            raise ValueError(f"lr_decay must be in (0, 1], got {self.lr_decay}")


def load_config(path: str | Path) -> RegisterConfig:
    """Read a :class:`RegisterConfig` from YAML; unknown keys and wrong types are one-line errors."""
    from blsm.config import config_from_dict

    return config_from_dict(RegisterConfig, read_yaml(path, "registration config"), str(path))
