"""The cost of event-branch variants in a training step, against the plain branch in the same run.

    python benchmarks/event_branch_step.py [--dataset ego] [--model events_only] [--batches 3] [--rounds 3]
        [--variants model.directional=true model.event_blocks=2 "model.event_blocks=2 model.directional=true"]

Each variant is the model of ``--model`` with the variant's config overrides (space-separated
within one argument). Every model runs forward and backward, in the trainer's CPU precision
(bfloat16 autocast where the CPU has it natively, else float32), on the same ``--batches``
training batches of 16 of ``--dataset`` (augmented as in training, the event graph built
beforehand), the models taking turns for ``--rounds`` rounds; each keeps its fastest round (the
machine is shared). Prints seconds per batch and each variant's ratio to the plain model.
"""
from __future__ import annotations

import argparse
import time

import torch

from dagr_lite.config import build_dataset, build_model, compose_config
from dagr_lite.data.collate import collate
from dagr_lite.engine.precision import cpu_has_bfloat16


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="ego")
    parser.add_argument("--model", default="events_only")
    parser.add_argument("--batches", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--variants", nargs="+", default=["model.directional=true", "model.event_blocks=2",
                                                          "model.event_blocks=2 model.directional=true"])
    args = parser.parse_args(argv)
    base = [f"dataset={args.dataset}", f"model={args.model}"]
    cfg = compose_config("train", base)
    data = build_dataset(cfg, "train", train=True, with_image=bool(cfg.model.use_image))
    batches = [collate([data[i] for i in range(b * 16, b * 16 + 16)]) for b in range(args.batches)]
    models = {}
    for variant in ["plain", *args.variants]:
        overrides = [] if variant == "plain" else variant.split()
        torch.manual_seed(0)
        models[variant] = build_model(compose_config("train", base + overrides), height=data.image_size[0],
                                      width=data.image_size[1]).train()
    spec = models["plain"].graph_spec
    for batch in batches:
        if spec is not None:
            batch.edge_index = spec.edges(batch.events, batch.batch_index)
    amp = torch.bfloat16 if cpu_has_bfloat16() else None
    print(f"{args.model} on {args.dataset}: {args.batches} batches of 16 ({sum(len(b.events) for b in batches):,} "
          f"events), forward + backward in {'float32' if amp is None else str(amp).split('.')[-1]}")
    best = {name: float("inf") for name in models}
    for _ in range(args.rounds):
        for name, model in models.items():
            start = time.perf_counter()
            for batch in batches:
                with torch.autocast("cpu", dtype=amp or torch.float32, enabled=amp is not None):
                    loss = model(batch)["loss"]
                loss.backward()
                model.zero_grad(set_to_none=True)
            best[name] = min(best[name], (time.perf_counter() - start) / len(batches))
    for name, seconds in best.items():
        print(f"{name:45s} {seconds:.3f} s per batch   {seconds / best['plain']:.2f}x the plain model")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
