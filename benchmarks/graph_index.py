"""The graph's index passes compiled (graph/sparse.py) against the sorts they replace, in the same run.

    python benchmarks/graph_index.py [--dataset ego] [--batches 3] [--rounds 5] [--models hybrid events_only]

On ``--batches`` training batches of 16 of ``--dataset`` (samples drawn at random, augmented and cropped as the recipe
trains, the event graph built beforehand as the loader's workers build it), times with the
compiled passes and without (``graph.sparse.USE_COMPILED`` off: ``torch.argsort`` and
``torch.unique``, what every other device runs), the two arms taking turns for ``--rounds``
rounds, each keeping its fastest (the machine is shared):
- the propagation matrix of the event graph and its transpose (what a training step builds for the
  first GCN stage, ``GraphOperator``);
- the first pooling, with the cells' edges (``voxel_max_pool`` at the first stride);
- a whole training step of each of ``--models`` (forward and backward, in the trainer's CPU
  precision: bfloat16 autocast where the CPU has it natively, else float32), the same weights
  in both arms.
Prints milliseconds a batch for each arm and the ratio (sorts / compiled).
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from dagr_lite.config import build_dataset, build_model, compose_config, graph_spec
from dagr_lite.data.collate import GraphCollate
from dagr_lite.engine.precision import cpu_has_bfloat16
from dagr_lite.graph import sparse
from dagr_lite.graph.pool import voxel_max_pool
from dagr_lite.nn.gcn import GraphOperator


def training_batches(cfg, count: int) -> list:
    """``count`` batches of 16 training samples of ``cfg``'s model (its events, and its frame and carry
    picture where it reads them), augmented as in training, with their event graphs."""
    torch.manual_seed(0)
    data = build_dataset(cfg, "train", train=True, with_image=bool(cfg.model.use_image))
    collate = GraphCollate(graph_spec(cfg.model))
    drawn = np.random.default_rng(0).choice(len(data), 16 * count, replace=False)  # as a shuffled epoch draws
    return [collate([data[(0, int(i))] for i in drawn[b * 16:(b + 1) * 16]]) for b in range(count)]


def fastest(work, rounds: int) -> tuple[float, float]:
    """Fastest seconds of ``work()`` with the compiled passes and without, the arms taking turns."""
    best = {True: float("inf"), False: float("inf")}
    try:
        for _ in range(rounds):
            for arm in (True, False):
                sparse.USE_COMPILED = arm
                start = time.perf_counter()
                work()
                best[arm] = min(best[arm], time.perf_counter() - start)
    finally:
        sparse.USE_COMPILED = True
    return best[True], best[False]


def report(label: str, compiled: float, sorts: float, batches: int) -> None:
    print(f"  {label:<44} compiled {1e3 * compiled / batches:7.1f} ms   sorts (baseline) "
          f"{1e3 * sorts / batches:7.1f} ms   {sorts / compiled:.2f}x", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="ego")
    parser.add_argument("--batches", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--models", nargs="+", default=["hybrid", "events_only"])
    args = parser.parse_args(argv)
    cfg = compose_config("train", [f"dataset={args.dataset}"])
    spec = graph_spec(cfg.model)
    batches = training_batches(cfg, args.batches)
    events = sum(len(b.events) for b in batches) / len(batches)
    edges = sum(b.edge_index.shape[1] for b in batches) / len(batches)
    print(f"{args.dataset}: {args.batches} training batches of 16, {events:,.0f} events and {edges:,.0f} edges a "
          f"batch; fastest of {args.rounds} rounds each, arms taking turns", flush=True)

    def operators():
        for b in batches:
            op = GraphOperator(b.edge_index, len(b.events))
            op.matrix(torch.float32), op.transposed(torch.float32)

    report("event graph: matrix and its transpose", *fastest(operators, args.rounds), len(batches))
    stride = cfg.model.strides[0]
    features = [torch.randn(len(b.events), 16) for b in batches]
    positions = [spec.positions(b.events) for b in batches]

    def pools():
        for b, x, pos in zip(batches, features, positions):
            voxel_max_pool(x, pos, b.batch_index, b.edge_index, stride)

    report(f"first pooling ({stride} px cells) with cell edges", *fastest(pools, args.rounds), len(batches))
    autocast = cpu_has_bfloat16()
    for name in args.models:
        model_cfg = compose_config("train", [f"dataset={args.dataset}", f"model={name}"])
        model_batches = training_batches(model_cfg, args.batches)
        height, width = model_batches[0].images.shape[-2:]  # a crop's, as the recipe trains
        model = build_model(model_cfg, height=int(height), width=int(width)).train()

        def steps():
            for b in model_batches:
                model.zero_grad(set_to_none=True)
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
                    loss = model(b)["loss"]
                loss.backward()

        steps()  # warm up
        report(f"{name}: training step (forward and backward)", *fastest(steps, args.rounds), len(batches))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
