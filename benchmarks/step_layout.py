"""Training steps on a CPU with channels-last weights and the fused AdamW, against neither.

    python benchmarks/step_layout.py [--dataset stub ego] [--variants hybrid events_only] [--steps 20] [--rounds 2]

Each arm trains ``--steps`` steps of batches of 16 training samples (the dataset's own recipe:
ego and the stub train on crops) as the trainer does: fed by the default loader (2 workers at
the trainer's lower priority, building the event graphs while the step runs), forward, backward
and AdamW, in float32, after 2 untimed warm-up steps (``benchmarks/cpu_step.py``'s timing). Arms:
the convolutions' weights contiguous or channels last (``trainer.channels_last``), the AdamW a
loop over tensors (PyTorch's default) or fused (``optim.fused``). The baseline, measured in the
same run, is contiguous with the loop: the trainer before both. The arms take turns for
``--rounds`` rounds and each keeps its fastest (the machine is shared); each arm's step alone, on
batches loaded beforehand with no workers running, is printed beside it.
"""
from __future__ import annotations

import argparse

import torch

from cpu_step import take_turns  # beside this script
from dagr_lite.config import build_dataset, build_model, compose_config, resolve_config, training_size

ARMS = (("contiguous, AdamW loop", False, None), ("channels last, AdamW loop", True, None),
        ("contiguous, AdamW fused", False, True), ("channels last, AdamW fused", True, True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", nargs="+", default=["stub", "ego"])
    parser.add_argument("--variants", nargs="+", default=["hybrid", "events_only"])
    parser.add_argument("--steps", type=int, default=20, help="timed steps per arm and round")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    print(f"{torch.get_num_threads()} torch threads; float32; batches of 16 training samples", flush=True)
    for dataset_name in args.dataset:
        for variant in args.variants:
            cfg = resolve_config(compose_config("train", [f"dataset={dataset_name}", f"model={variant}"]))
            dataset = build_dataset(cfg, "train", train=True, with_image=cfg.model.use_image)
            height, width = training_size(cfg, dataset.image_size)
            workers, nice = int(cfg.loader.num_workers), int(cfg.loader.worker_nice)
            arms = []
            for name, last, fused in ARMS:
                torch.manual_seed(0)
                model = build_model(cfg, height=height, width=width).train()
                if last:
                    model = model.to(memory_format=torch.channels_last)
                arms.append((name, model, torch.optim.AdamW(model.parameters(), lr=1e-4, fused=fused)))
            best, alone = take_turns([(model, optimizer, None) for _, model, optimizer in arms], dataset, args.steps,
                                     args.rounds, workers, nice)
            print(f"{dataset_name} {variant} ({height}x{width} crops, {workers} loader workers at nice {nice}):")
            for (name, *_), seconds, own in zip(arms, best, alone):
                print(f"  {name:28s} {seconds:6.3f} s/step, {best[0] / seconds:4.2f}x the steps of {arms[0][0]} "
                      f"(the step alone {own:5.3f} s, {alone[0] / own:4.2f}x)", flush=True)


if __name__ == "__main__":
    main()
