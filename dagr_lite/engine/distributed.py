"""Training on several processes with torch's DistributedDataParallel (``torchrun``).

``torchrun --nproc_per_node=N train.py ...`` sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK`` and
the rendezvous; :func:`setup` joins the process group (NCCL on CUDA, Gloo on CPU) and picks the
device. Rank 0 alone writes (run folder, logs, progress bar, TensorBoard, checkpoints). Each
step's global batch is ``loader.batch_size x world_size`` samples, one slice per rank; the
losses are normalised by the foreground count of the global batch and batch norm takes its
statistics over the global batch, so N processes train like one process with the global batch.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

from dagr_lite.errors import UserError


@dataclass(frozen=True)
class Distributed:
    """This process's place in the group (``world_size`` 1: a single process)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @classmethod
    def from_environment(cls) -> "Distributed":
        """The place ``torchrun`` (or any launcher setting ``RANK``/``WORLD_SIZE``) gave this process."""
        values = {}
        for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
            text = os.environ.get(key)
            try:
                values[key] = int(text) if text is not None else None
            except ValueError:
                raise UserError(f"environment variable {key}={text!r} must be an integer (set by torchrun)") from None
        world = values["WORLD_SIZE"] or 1
        rank = values["RANK"] or 0
        if not 0 <= rank < world:
            raise UserError(f"RANK={rank} must be in [0, WORLD_SIZE={world})")
        return cls(rank=rank, world_size=world, local_rank=values["LOCAL_RANK"] or 0)


def setup(place: Distributed, device: torch.device) -> torch.device:
    """Join the process group (once) and return this rank's device (``cuda:<local_rank>`` on CUDA)."""
    if not place.enabled:
        return device
    if device.type == "cuda":
        gpus = torch.cuda.device_count()
        if place.local_rank >= gpus:
            raise RuntimeError(f"rank {place.rank} has LOCAL_RANK {place.local_rank}, so it needs GPU {place.local_rank}, "
                               f"but this machine has {gpus} GPU(s): start at most {gpus} processes per machine "
                               f"(torchrun --nproc_per_node {gpus}), or train on the CPU with device=cpu")
        device = torch.device("cuda", place.local_rank)
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        # torchrun's store outlives a restarted group: keys of each attempt get their own prefix, so
        # a restarted rank never reads the address of a process that died.
        store, rank, world = next(dist.rendezvous("env://"))
        attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=rank, world_size=world,
                                store=dist.PrefixStore(f"dagr_lite/attempt{attempt}", store))
    if dist.get_world_size() != place.world_size:
        raise RuntimeError(f"the process group has {dist.get_world_size()} ranks, WORLD_SIZE says {place.world_size}")
    return device


def cleanup(place: Distributed) -> None:
    if place.enabled and dist.is_initialized():
        dist.destroy_process_group()


def broadcast_object(value, place: Distributed):
    """Rank 0's ``value`` on every rank."""
    if not place.enabled:
        return value
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def gather_objects(value, place: Distributed) -> list:
    """Every rank's ``value``, in rank order, on every rank."""
    if not place.enabled:
        return [value]
    values = [None] * place.world_size
    dist.all_gather_object(values, value)
    return values


def mean_over_ranks(values: dict[str, torch.Tensor], place: Distributed) -> dict[str, torch.Tensor]:
    """Scalars averaged over the ranks: with the global normaliser, the mean of the ranks' losses
    is the loss of the global batch, as one process would report it."""
    if not place.enabled:
        return values
    keys = sorted(values)
    stacked = torch.stack([values[k].detach().double().reshape(()) for k in keys])
    dist.all_reduce(stacked)
    stacked /= place.world_size
    return {k: stacked[i].to(values[k].dtype) for i, k in enumerate(keys)}


def global_normaliser(place: Distributed):
    """The loss normaliser of a global batch: given this rank's foreground count, returns
    ``max(total count, 1) / world_size``, so that DDP's gradient average equals the gradient of
    one process holding the whole batch (None for a single process)."""
    if not place.enabled:
        return None

    def normaliser(num_fg: float) -> float:
        total = torch.tensor([float(num_fg)], dtype=torch.float64)
        if dist.get_backend() == "nccl":  # NCCL reduces tensors on this rank's GPU
            total = total.to(torch.device("cuda", torch.cuda.current_device()))
        dist.all_reduce(total)
        return max(float(total.item()), 1.0) / place.world_size

    return normaliser


class GlobalBatchNorm2d(nn.BatchNorm2d):
    """Batch norm with statistics over every rank's batch, for CPU process groups (torch's
    ``SyncBatchNorm`` needs a GPU). In evaluation it is plain batch norm; its state dict is
    batch norm's."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or not dist.is_initialized():
            return super().forward(x)
        channels = x.shape[1]
        count = x.new_tensor([x.numel() / channels])
        local = torch.cat([x.sum(dim=(0, 2, 3)), (x * x).sum(dim=(0, 2, 3)), count])
        total = _all_reduce_with_gradient(local)  # summed over ranks
        n = total[-1]
        mean = total[:channels] / n
        var = (total[channels:2 * channels] / n - mean * mean).clamp(min=0)
        with torch.no_grad():
            self.num_batches_tracked += 1
            momentum = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
            self.running_mean.mul_(1 - momentum).add_(momentum * mean.detach())
            self.running_var.mul_(1 - momentum).add_(momentum * var.detach() * n / (n - 1).clamp(min=1))
        shape = (1, channels, 1, 1)
        y = (x - mean.view(shape)) * torch.rsqrt(var.view(shape) + self.eps)
        return y * self.weight.view(shape) + self.bias.view(shape) if self.affine else y


def _all_reduce_with_gradient(x: torch.Tensor) -> torch.Tensor:
    """Sum over ranks; the gradient of each rank's input is the sum of every rank's output gradient."""
    return _AllReduceSum.apply(x)


class _AllReduceSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        out = x.clone()
        dist.all_reduce(out)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        grad = grad.clone()
        dist.all_reduce(grad)
        return grad


def synchronise_batch_norm(model: nn.Module, device: torch.device) -> nn.Module:
    """``model`` with every batch norm taking its statistics over all ranks."""
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(model)
    for name, child in model.named_children():
        if type(child) is nn.BatchNorm2d:
            replacement = GlobalBatchNorm2d(child.num_features, child.eps, child.momentum, child.affine,
                                            child.track_running_stats).to(child.weight.device)
            replacement.load_state_dict(child.state_dict())
            setattr(model, name, replacement)
        else:
            synchronise_batch_norm(child, device)
    return model
