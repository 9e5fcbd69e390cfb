"""The precision of a training step: mixed precision where the device computes it natively."""
from __future__ import annotations

import torch

from dagr_lite.config import TrainerSettings


def cpu_has_bfloat16() -> bool:
    """Whether this CPU computes in bfloat16 natively (AVX512-BF16 or AMX), so that bfloat16
    convolutions are faster than float32 ones; elsewhere they are emulated and slower."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in checks)


def amp_dtype(trainer: TrainerSettings, device: torch.device) -> torch.dtype | None:
    """The mixed precision of a training step when ``trainer.amp`` (None: float32).

    CUDA: ``trainer.amp_dtype`` (``auto``: bfloat16 where the GPU supports it, else float16 with
    the gradient scaler). CPU: bfloat16 where the CPU has it natively (``auto`` or ``bfloat16``;
    float16 is not offered there), else float32. The sparse graph products and the losses run in
    float32 either way.
    """
    if not trainer.amp or device.type not in ("cuda", "cpu"):
        return None
    if device.type == "cpu":
        return torch.bfloat16 if trainer.amp_dtype in ("auto", "bfloat16") and cpu_has_bfloat16() else None
    if trainer.amp_dtype == "auto":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    return {"float16": torch.float16, "bfloat16": torch.bfloat16}[trainer.amp_dtype]
