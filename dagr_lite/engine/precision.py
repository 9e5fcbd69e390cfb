"""The precision of a training step: mixed precision where the device computes it natively, and on
a CPU only where it also makes the step clearly faster; and the layout its convolutions' weights take."""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import torch

from dagr_lite.config import TrainerSettings


def cpu_has_bfloat16() -> bool:
    """Whether this CPU computes in bfloat16 natively (AVX512-BF16 or AMX); elsewhere bfloat16 is
    emulated and slower than float32. Native is not always faster: on some CPUs with AVX512-BF16
    alone the model's small convolutions run slower in bfloat16 (see :func:`time_precisions`)."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in checks)


def amp_dtype(trainer: TrainerSettings, device: torch.device) -> torch.dtype | None:
    """The mixed precision of a training step when ``trainer.amp`` (None: float32).

    CUDA: ``trainer.amp_dtype`` (``auto``: bfloat16 where the GPU supports it, else float16 with
    the gradient scaler). CPU: bfloat16 where the CPU has it natively (``auto`` or ``bfloat16``;
    float16 is not offered there), else float32; with ``auto`` a run then keeps bfloat16 only if
    :func:`time_precisions` finds it clearly faster (:data:`BFLOAT16_MARGIN`; :func:`prefers_trial`
    says when to ask). The sparse graph products and the losses run in float32 either way.
    """
    if not trainer.amp or device.type not in ("cuda", "cpu"):
        return None
    if device.type == "cpu":
        return torch.bfloat16 if trainer.amp_dtype in ("auto", "bfloat16") and cpu_has_bfloat16() else None
    if trainer.amp_dtype == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"float16": torch.float16, "bfloat16": torch.bfloat16}[trainer.amp_dtype]


def memory_format(trainer: TrainerSettings, device: torch.device) -> torch.memory_format:
    """How a training run stores its convolutions' weights (and so their maps): channels last where
    ``trainer.channels_last`` asks for it (``auto``: on a CPU, whose convolution kernels run it
    faster: with the fused AdamW, a step alone 1.08-1.17 times faster on 2 cores,
    ``benchmarks/step_layout.py``), else contiguous. The weights are the same numbers either way;
    a step's results differ by rounding."""
    chosen = trainer.channels_last
    on = device.type == "cpu" if chosen == "auto" else bool(chosen)
    return torch.channels_last if on else torch.contiguous_format


def prefers_trial(trainer: TrainerSettings, device: torch.device) -> bool:
    """Whether a run chooses its precision by timing a step in each (:func:`time_precisions`): a
    CPU with native bfloat16 and ``amp_dtype: auto``."""
    return amp_dtype(trainer, device) == torch.bfloat16 and device.type == "cpu" and trainer.amp_dtype == "auto"


# bfloat16 is chosen only when the trial's step takes under this fraction of float32's. The trial
# times a step alone; in a run the loader's workers share the cores, and on a CPU where the trial
# found bfloat16 5-7% faster, runs in bfloat16 made fewer steps than runs in float32 (docs/results.md,
# 2026-12-01): a trial within a tenth does not tell which run is faster, and float32 is then kept.
BFLOAT16_MARGIN = 0.9


@dataclass(frozen=True)
class PrecisionTrial:
    """Seconds of one training step's forward and backward in each precision, on this CPU; for a
    run with a first phase, the mean step of its schedule (:meth:`of_schedule`), and ``parts``
    the phase's share and trial, then the rest's."""

    float32_s: float
    bfloat16_s: float
    parts: tuple[tuple[float, "PrecisionTrial"], ...] = ()

    @classmethod
    def of_schedule(cls, first: "PrecisionTrial", share: float, rest: "PrecisionTrial", *,
                    by_time: bool) -> "PrecisionTrial":
        """The mean step of a run whose first ``share`` of the schedule takes ``first``'s steps and
        the rest ``rest``'s. ``by_time`` (``schedule_by: time``): the shares are of the run's time,
        so the precision that makes more steps in it is faster: the harmonic mean
        ``1 / (share / first + (1 - share) / rest)``; otherwise of its steps, the arithmetic mean."""
        def mean(a: float, b: float) -> float:
            return 1.0 / (share / a + (1 - share) / b) if by_time else share * a + (1 - share) * b

        return cls(float32_s=mean(first.float32_s, rest.float32_s), bfloat16_s=mean(first.bfloat16_s, rest.bfloat16_s),
                   parts=((share, first), (1 - share, rest)))

    @property
    def dtype(self) -> torch.dtype | None:
        """``torch.bfloat16`` when it took under :data:`BFLOAT16_MARGIN` of float32's time, else None (float32)."""
        return torch.bfloat16 if self.bfloat16_s < BFLOAT16_MARGIN * self.float32_s else None

    def describe(self, phase: str = "the first phase") -> str:
        """What was timed and the rule; ``phase`` names the first phase of a schedule's trial."""
        took = f"{self.float32_s:.3f} s in float32 and {self.bfloat16_s:.3f} s in bfloat16"
        if self.parts:
            (share, first), (_, rest) = self.parts
            took = (f"a step of the run's schedule took {took} on this CPU (its first {100 * share:.3g}%, {phase}: "
                    f"{first.float32_s:.3f} s and {first.bfloat16_s:.3f} s; the rest: {rest.float32_s:.3f} s and "
                    f"{rest.bfloat16_s:.3f} s)")
        else:
            took = f"a step's forward and backward took {took} on this CPU"
        return f"{took}; bfloat16 only if it takes under {BFLOAT16_MARGIN:g} of float32's time"


def time_precisions(model: torch.nn.Module, batch, *, rounds: int = 3, **branches: bool) -> PrecisionTrial:
    """Time the forward and backward of a training step on ``batch`` in float32 and in bfloat16
    autocast, on a copy of ``model`` (its weights, batch-norm statistics and gradients stay as they
    are; the random state is restored). After one warm-up each, the two take turns for ``rounds``
    rounds and each keeps its fastest, so a busy moment of a shared machine counts against neither.
    ``model`` must make no collective calls (time it before batch norm or the loss normaliser are
    shared between processes). ``branches``: the model's branch flags (``image``, ``events``,
    ``graph``), as a first phase's steps run (``config.PHASE_STEP``)."""
    trial = copy.deepcopy(model).train()
    best = {None: float("inf"), torch.bfloat16: float("inf")}

    def step(dtype: torch.dtype | None) -> float:
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype is not None):
            loss = trial(batch, **branches)["loss"]
        loss.backward()
        seconds = time.perf_counter() - start
        trial.zero_grad(set_to_none=True)
        return seconds

    with torch.random.fork_rng(devices=[]):
        for dtype in best:
            step(dtype)
        for _ in range(rounds):
            for dtype in best:
                best[dtype] = min(best[dtype], step(dtype))
    return PrecisionTrial(float32_s=best[None], bfloat16_s=best[torch.bfloat16])
