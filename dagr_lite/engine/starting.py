"""Where a run starts: resuming a checkpoint (``resume=``, or a torchrun group restarted in its own
folder), starting from another checkpoint's weights (``init_from=``), and the run folder every rank
shares."""
from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from dagr_lite.errors import UserError
from dagr_lite.engine.checkpoint import Checkpoint, load_checkpoint
from dagr_lite.engine.distributed import Distributed, broadcast_object
from dagr_lite.engine.runs import run_folder
from dagr_lite.engine.state import TrainState
from dagr_lite.nn.warm_start import warm_start


class ResumeError(UserError):
    """A checkpoint given as ``resume=`` does not fit this run; the message names both sides."""


def resume(state: TrainState, path: str | Path, checkpoints: Path, place: Distributed) -> Checkpoint:
    """Continue from checkpoint ``path``; its run's ``best.pt`` is carried into ``checkpoints`` (by
    rank 0), so the new run holds its best weights even when it never beats them. Returns the
    checkpoint (its ``position`` says where in the data it stopped)."""
    saved = load_checkpoint(path)
    ours, theirs = state.detector_cfg.as_dict(), saved.detector.as_dict()
    if theirs != ours:
        differ = ", ".join(f"{key}: {theirs[key]!r} in the checkpoint, {ours[key]!r} here"
                           for key in ours if theirs[key] != ours[key])
        raise ResumeError(f"resume={path}: the checkpoint's model does not fit this run's ({differ}); a resumed "
                          "run takes its model from its own overrides.yaml: leave out the model= and model.* "
                          "overrides that change it (init_from= starts a new run from its weights)")
    groups = saved.training["optimizer"]["param_groups"]
    if groups and set(groups[0]) - {"params"} != set(state.optimizer.param_groups[0]) - {"params"}:
        name = str((saved.config.get("optim") or {}).get("_target_", "another optimizer")).rsplit(".", 1)[-1]
        raise ResumeError(f"resume={path}: the run was trained with {name}, this run's optimizer is "
                          f"{type(state.optimizer).__name__}; its state cannot continue here (init_from={path} "
                          "starts a new run from its weights)")
    state.load_state_dict(saved.training)
    best = Path(path).parent / "best.pt"
    if best.is_file():
        if place.is_main and best.resolve() != (checkpoints / "best.pt").resolve():
            checkpoints.mkdir(parents=True, exist_ok=True)
            shutil.copy2(best, checkpoints / "best.pt")
    else:
        state.best_metric = -math.inf  # nothing to carry: the first validation writes best.pt
    if place.is_main:
        ranks = saved.training.get('world_size', 1)
        print(f"resumed from {path} at step {state.step} (it ran on {ranks} process{'es' if ranks != 1 else ''})",
              flush=True)
    return saved


def resumed_config(cfg: DictConfig) -> DictConfig:
    """With ``resume=RUN/checkpoints/last.pt`` on a command line: the run's own overrides
    (``RUN/overrides.yaml``) composed first and the command line's after them, so the checkpoint's
    model, data and recipe come back without being repeated and any of them can still be changed;
    the run goes on in its own folder unless ``run_dir=`` names another. Anything else (no
    ``resume``, no saved overrides, a config not made by a Hydra command) is returned as it is."""
    if cfg.get("resume") is None:
        return cfg
    try:
        from hydra.core.hydra_config import HydraConfig
        command = list(HydraConfig.get().overrides.task)
    except (ImportError, ValueError):
        return cfg
    run = Path(cfg.resume).parent.parent
    saved = run / "overrides.yaml"
    if not saved.is_file():
        return cfg
    theirs = [str(o) for o in OmegaConf.load(saved) if not str(o).startswith(("resume=", "init_from="))]
    if not any(o.startswith("run_dir=") for o in command):
        command.append(f"run_dir={run}")
    from hydra import compose
    return compose(config_name="train", overrides=theirs + command)


def continues_own_run(cfg: DictConfig) -> bool:
    """Whether ``resume=`` names a checkpoint of the run folder this run writes into."""
    if cfg.get("resume") is None or not cfg.get("run_dir"):
        return False
    return Path(cfg.resume).resolve().parent.parent == Path(cfg.run_dir).resolve()


def shared_run_folder(cfg: DictConfig, place: Distributed) -> tuple[Path, Path | None]:
    """The run folder, checked by rank 0 and shared with every rank (nothing is written yet:
    :func:`_train` makes it once the data, model and state are built), and the checkpoint to
    resume from: ``resume=``, or, when torchrun restarts a failed group, the run's own ``last.pt``.
    A folder that holds a run is refused, but for the run that ``resume=`` continues."""
    restarted = int(os.environ.get("TORCHELASTIC_RESTART_COUNT", "0") or 0) > 0
    outcome = None
    if place.is_main:
        try:
            own = own_last_checkpoint(cfg) if restarted else None
            if own:
                folder = own.parent.parent
            else:
                folder = Path(cfg.run_dir) if continues_own_run(cfg) else run_folder(cfg, "train", make=False)
            outcome = ("ok", str(folder), own and str(own))
        except Exception as err:  # rank 0 refuses the run: every rank must stop, not wait
            outcome = ("error", f"{type(err).__name__}: {err}", None)
            broadcast_object(outcome, place)
            raise
    outcome = broadcast_object(outcome, place)
    if outcome[0] == "error":
        raise RuntimeError(f"rank 0 refused the run: {outcome[1]}")
    resume_from = outcome[2] or cfg.resume
    return Path(outcome[1]), Path(resume_from) if resume_from else None


def own_last_checkpoint(cfg: DictConfig) -> Path | None:
    """This run's ``checkpoints/last.pt`` when its folder already holds one (a restarted group)."""
    if cfg.get("run_dir"):
        folder = Path(cfg.run_dir)
    else:
        from hydra.core.hydra_config import HydraConfig
        folder = Path(HydraConfig.get().runtime.output_dir)
    last = folder / "checkpoints" / "last.pt"
    return last if last.is_file() else None


def start_weights(cfg: DictConfig, resume_from: Path | None) -> str | None:
    """The checkpoint ``init_from`` names, when this run starts from it: not when it resumes (a
    run restarted in its own folder continues from its own ``last.pt``, which holds what training
    made of those weights; ``check_values`` refuses ``init_from`` beside ``resume``)."""
    path = cfg.get("init_from")
    return None if path is None or resume_from is not None else str(path)


def start_from(model, path: str | Path, *, verbose: bool = True) -> dict:
    """Start ``model`` from the weights of checkpoint ``path`` (its EMA weights, the ones it was
    validated with) that fit, :func:`~dagr_lite.nn.warm_start.warm_start`."""
    saved = load_checkpoint(path)
    report = warm_start(model, saved.weights)
    if not report["copied"] and not report["widened"]:
        raise UserError(f"init_from={path}: no weight of that checkpoint ({saved.model_name}) fits this model; "
                         "nothing to start from")
    if verbose:
        print(f"init_from {path}: {len(report['copied'])} tensors copied, {len(report['widened'])} widened "
              f"with zeros, {len(report['kept'])} at their own initialisation", flush=True)
        note = graph_note(saved.detector.graph, model.graph_spec)
        if note:
            print(f"init_from {path}: {note}", flush=True)
    return report


def graph_note(theirs, ours) -> str | None:
    """What a run started from a checkpoint reads differently, when the checkpoint's event graph
    (an ``EventGraphSpec``) is not this model's (the events-only model's default graph is smaller
    than the hybrid's): its weights then read another graph than they were trained on. None when
    both are the same or either model has no event branch."""
    if theirs is None or ours is None or theirs == ours:
        return None
    return (f"the checkpoint's event graph (radius {theirs.radius:g} px, {theirs.max_neighbors} neighbours, beta "
            f"{theirs.beta:g}) is not this run's (radius {ours.radius:g}, {ours.max_neighbors}, beta {ours.beta:g}): "
            f"its weights read this run's graph; model.graph.radius={theirs.radius:g} "
            f"model.graph.max_neighbors={theirs.max_neighbors} model.graph.beta={theirs.beta:g} keep its own")
