"""The training camera's exposure, learned from the footage (`TrainConfig.fit_exposure`).

A video rarely says how long its shutter stayed open (the shared clips carry no such metadata,
and ingest assumes 0.5 of the frame interval), yet K.R. blurs each dynamic Gaussian over
`|v| dt exposure`. Here the exposure is one scalar, `sigmoid(logit)` so that it stays inside
(0, 1), fitted by the photometric loss with everything else. It has a gradient only where
something is blurred: the dynamic set after the decomposition (and every Gaussian under
`camera_blur`). What it measures is the blur length the model needs per unit of its own
velocity, so when the learned velocities fall short of the true motion the fitted exposure
rises to make up the blur (docs/real-footage.md, "Exposure")."""

from __future__ import annotations

import math

import torch

# The logit starts from the given exposure clipped into this range: at 0 or 1 the sigmoid's
# gradient vanishes and the fit could not move.
START_RANGE = (0.05, 0.95)


class FittedExposure:
    def __init__(self, start: float):
        e = min(max(float(start), START_RANGE[0]), START_RANGE[1])
        self.start = float(start)
        self.logit = torch.nn.Parameter(torch.tensor(math.log(e / (1 - e))))

    def to(self, device) -> "FittedExposure":
        self.logit = torch.nn.Parameter(self.logit.detach().to(device))
        return self

    def value(self) -> torch.Tensor:
        """The exposure as a 0-d tensor with its gradient path to `logit`."""
        return torch.sigmoid(self.logit)

    def __float__(self) -> float:
        return float(torch.sigmoid(self.logit.detach()))

    def state_dict(self) -> dict:
        return {"logit": self.logit.detach().clone(), "start": self.start}

    def load_state_dict(self, state: dict) -> None:
        with torch.no_grad():
            self.logit.copy_(state["logit"])
        self.start = float(state["start"])
