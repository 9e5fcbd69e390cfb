"""What moves the weights besides the optimiser: the EMA of the weights and the learning-rate schedule."""
from __future__ import annotations

import copy
import math

import torch
from torch import nn


class ModelEMA:
    """Exponential moving average of a model's weights (and buffers), used for validation.

    ``decay`` ramps up as ``decay * (1 - exp(-updates / tau))`` so early averages follow the model.
    """

    def __init__(self, model: nn.Module, decay: float, tau: float):
        self.module = copy.deepcopy(model).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, 0

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        model_state = model.state_dict()
        for name, value in self.module.state_dict().items():
            if value.dtype.is_floating_point:
                value.mul_(d).add_(model_state[name].detach(), alpha=1 - d)
            else:
                value.copy_(model_state[name])

    def state_dict(self) -> dict:
        return {"module": self.module.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.module.load_state_dict(state["module"])
        self.updates = int(state["updates"])


def warmup_cosine(step: int, *, warmup: int, total: int, min_ratio: float, progress: float | None = None) -> float:
    """Learning-rate factor: linear warm-up over ``warmup`` steps, then cosine down to ``min_ratio``.

    The cosine's progress is ``(step - warmup) / (total - warmup)``; ``progress``, when given, is a
    second measure (e.g. the fraction of a time budget spent since the warm-up), and the cosine
    follows whichever of the two is further along."""
    if step < warmup:
        return (step + 1) / warmup
    by_steps = (step - warmup) / max(1, total - warmup)
    progress = min(1.0, max(by_steps, progress if progress is not None else 0.0))
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))
