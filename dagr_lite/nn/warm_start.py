"""Starting a model from another model's weights: every tensor whose name and shape match, and
event-branch layers that read more inputs here than in the source widened with zeros (more
inputs only: a layer with more outputs, as in a larger model size, keeps its own initialisation).

The event branch lays out each GCN stage's input as the source's inputs first (polarity, x, y,
then the previous stage's channels) and what a hybrid adds after them (the node's time since the
image at the first stage, the image channels sampled at the nodes at every stage). A layer of an
events-only model therefore fits into the same layer of a hybrid: its weights for the shared
inputs are copied and those for the added inputs are zero, so the hybrid's event nodes start out
computing exactly what the events-only model's do, and learn to use the time and the image from there.
"""
from __future__ import annotations

import torch
from torch import nn

WIDENED_PREFIX = "events."  # only here is the input layout known to put the source's inputs first
# The input dimension of the event branch's layers: a GCN weight is (in, out), its offset weights (3, in, out),
# a skip projection (out, in).
INPUT_DIM = {"conv.weight": 0, "conv.weight_offsets": 1, "skip.weight": 1}


def widen(source: torch.Tensor, shape: torch.Size, dim: int | None = None) -> torch.Tensor | None:
    """``source`` placed at the start of a zero tensor of ``shape``, when the two differ in one
    dimension only (``dim``, where given) and ``source`` is the smaller there; else None."""
    if source.dim() != len(shape):
        return None
    differ = [d for d in range(source.dim()) if source.shape[d] != shape[d]]
    if len(differ) != 1 or source.shape[differ[0]] > shape[differ[0]] or dim not in (None, differ[0]):
        return None
    out = torch.zeros(shape, dtype=source.dtype)
    out.narrow(differ[0], 0, source.shape[differ[0]]).copy_(source)
    return out


def _identity_skip(name: str, source: dict[str, torch.Tensor], shape: torch.Size) -> torch.Tensor | None:
    """A GCN block's skip projection ``(out, in)`` that the source block did not need (its input
    was as wide as its output, so its skip was the identity): the identity on the source's inputs."""
    if not name.endswith(".skip.weight"):
        return None
    conv = source.get(name[: -len("skip.weight")] + "conv.weight")  # (in, out) of the source block
    if conv is None or conv.dim() != 2 or conv.shape[0] != conv.shape[1] or shape[0] != conv.shape[1]:
        return None
    return widen(torch.eye(conv.shape[1], dtype=conv.dtype), shape, INPUT_DIM["skip.weight"])


def warm_start(model: nn.Module, source: dict[str, torch.Tensor]) -> dict[str, list[str]]:
    """Copy into ``model`` the tensors of the state dict ``source`` that fit (see the module notes).

    Returns the names ``{"copied": [...], "widened": [...], "kept": [...]}``: copied as they are,
    widened with zeros, and left at the model's own initialisation (absent from ``source``, of a
    shape that does not fit, or a counter such as batch norm's ``num_batches_tracked``).
    """
    own = model.state_dict()
    report = {"copied": [], "widened": [], "kept": []}
    for name, target in own.items():
        value = source.get(name)
        if not target.is_floating_point():  # counters (batch norm's num_batches_tracked) start afresh
            report["kept"].append(name)
            continue
        if value is not None and value.shape == target.shape:
            target.copy_(value)
            report["copied"].append(name)
            continue
        wide, dim = None, INPUT_DIM.get(".".join(name.split(".")[-2:]))
        if name.startswith(WIDENED_PREFIX) and dim is not None:  # more inputs; never more outputs
            wide = widen(value, target.shape, dim) if value is not None else _identity_skip(name, source, target.shape)
        if wide is not None:
            target.copy_(wide)
            report["widened"].append(name)
        else:
            report["kept"].append(name)
    return report
