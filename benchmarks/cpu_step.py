"""Training steps on a CPU in each precision and image stem, against float32 with the conv stem.

    python benchmarks/cpu_step.py [--steps 20] [--rounds 2] [--variants hybrid events_only]

Each arm trains ``--steps`` steps on the stub dataset's training samples as the trainer does:
batches of 16 from the default loader (2 workers at the trainer's lower priority, building the
event graphs while the step runs), forward, backward and AdamW, timed from the first batch
asked for to the last step done (after 2 untimed warm-up steps). The arms take turns for
``--rounds`` rounds and each keeps its fastest (the machine is shared). Arms: ``float32`` or
``bfloat16`` autocast (printed: whether the CPU has it natively; the trainer takes the faster),
and for a model with an image the image stem ``conv`` (two 3x3 convolutions of stride 2) or
``patch`` (one 4x4 convolution of stride 4). The baseline, measured in the same run, is float32
with the conv stem: the default before both. Each arm's step alone, on batches loaded
beforehand with no workers running, is printed beside it: the difference is what the loader's
workers take from the step on the same cores.
"""
from __future__ import annotations

import argparse
import time

import torch

from dagr_lite.config import build_dataset, build_model, compose_config, resolve_config
from dagr_lite.engine.loading import make_loader
from dagr_lite.engine.precision import cpu_has_bfloat16


def step(model, optimizer, batch, dtype: torch.dtype | None) -> None:
    with torch.autocast("cpu", dtype=dtype or torch.bfloat16, enabled=dtype is not None):
        out = model(batch)
    optimizer.zero_grad(set_to_none=True)
    out["loss"].backward()
    optimizer.step()


def timed_steps(model, optimizer, dataset, dtype, steps: int, workers: int, nice: int) -> float:
    """Seconds per step over ``steps`` steps fed by a fresh loader (after 2 warm-up steps)."""
    loader = make_loader(dataset, batch_size=16, num_workers=workers, graph=model.graph_spec, worker_nice=nice)
    iterator = iter(loader)
    for _ in range(2):
        step(model, optimizer, next(iterator), dtype)
    start = time.perf_counter()
    for _ in range(steps):
        step(model, optimizer, next(iterator), dtype)
    seconds = (time.perf_counter() - start) / steps
    del iterator  # the workers stop
    return seconds


def steps_alone(model, optimizer, batches, dtype) -> float:
    """Seconds per step on ``batches`` loaded beforehand (no loader running)."""
    start = time.perf_counter()
    for batch in batches:
        step(model, optimizer, batch, dtype)
    return (time.perf_counter() - start) / len(batches)


def take_turns(arms, dataset, steps: int, rounds: int, workers: int, nice: int) -> tuple[list[float], list[float]]:
    """Each arm ``(model, optimizer, dtype)``'s fastest seconds per step over ``rounds`` turns: fed
    by a fresh loader (:func:`timed_steps`), and alone on 6 batches loaded beforehand (:func:`steps_alone`)."""
    iterator = iter(make_loader(dataset, batch_size=16, num_workers=0, graph=arms[0][0].graph_spec))
    loaded = [next(iterator) for _ in range(6)]
    best, alone = [float("inf")] * len(arms), [float("inf")] * len(arms)
    for _ in range(rounds):
        for i, (model, optimizer, dtype) in enumerate(arms):
            best[i] = min(best[i], timed_steps(model, optimizer, dataset, dtype, steps, workers, nice))
            alone[i] = min(alone[i], steps_alone(model, optimizer, loaded, dtype))
    return best, alone


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20, help="timed steps per arm and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--variants", nargs="+", default=["hybrid", "events_only"])
    args = parser.parse_args()
    defaults = resolve_config(compose_config("train", []))
    workers, nice = int(defaults.loader.num_workers), int(defaults.loader.worker_nice)
    print(f"CPU with native bfloat16: {cpu_has_bfloat16()}; {torch.get_num_threads()} torch threads; "
          f"batches of 16 stub training samples, {workers} loader workers at nice {nice}", flush=True)
    for variant in args.variants:
        cfg = resolve_config(compose_config("train", [f"model={variant}"]))
        dataset = build_dataset(cfg, "train", train=True, with_image=cfg.model.use_image)
        height, width = dataset.image_size
        stems = ["conv", "patch"] if cfg.model.use_image else [None]
        arms = []
        for stem in stems:
            overrides = [f"model={variant}"] + ([f"model.image_stem={stem}"] if stem else [])
            for dtype in (None, torch.bfloat16):
                torch.manual_seed(0)
                model = build_model(resolve_config(compose_config("train", overrides)), height=height, width=width)
                name = f"{variant} {'stem ' + stem if stem else ''} {'bfloat16' if dtype else 'float32'}"
                arms.append((" ".join(name.split()), model.train(), torch.optim.AdamW(model.parameters(), lr=1e-4),
                             dtype))
        best, alone = take_turns([arm[1:] for arm in arms], dataset, args.steps, args.rounds, workers, nice)
        for (name, *_), seconds, own in zip(arms, best, alone):
            print(f"{name:32s} {seconds:6.3f} s/step, {best[0] / seconds:4.2f}x the step of {arms[0][0]} "
                  f"(the step alone {own:5.3f} s, {alone[0] / own:4.2f}x)", flush=True)


if __name__ == "__main__":
    main()
