"""Detection quality against the image's age, for several checkpoints on the same frames.

    python -m dagr_lite.apps.sweep ckpt=[A.pt,B.pt] split=test ages=[1,2,3,5,7,10] out=DIR [between=10] [stream=true]

Every checkpoint is scored at every image age ``a`` (the image of frame ``k - a`` and the
events of the sample's horizon, boxes of frame ``k``) on one list of label frames, ``k >= max(ages)``, so the
rows compare. With ``between=N`` each age is also scored at the ``N - 1`` times between label
frames ``k`` and ``k + 1`` (every ``1/N`` of a frame interval), against boxes interpolated
linearly between the two frames (:func:`interpolate_boxes`); only frame pairs whose boxes all
match are used. With ``stream=true`` each point scores what the streaming detector answers when
fed as a camera feeds it (:func:`streamed_detections`); it reads the same sample as the batch
model, so the figures agree (tests/apps/test_sweep_stream.py). Each point also gives the recall
of the hands that moved since the image and of those that did not (:func:`moved_recall`, at the
checkpoint's operating point): what carrying the image forward is about. Writes ``sweep.json``,
``sweep.csv`` and ``sweep.png`` into ``out`` and prints the table.
"""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from scipy.optimize import linear_sum_assignment
from torch.utils.data import Dataset

from dagr_lite.apps.cli import hydra_command
from dagr_lite.config import ConfigError, build_dataset, resolve_config
from dagr_lite.data import format as fmt
from dagr_lite.data.dataset import EventEgoHands, Sample
from dagr_lite.engine.loading import make_loader
from dagr_lite.engine.runs import resolve_device, run_folder
from dagr_lite.data.writer import write_text_atomically
from dagr_lite.data.spec import SampleSpec
from dagr_lite.engine.checkpoint import Checkpoint, check_picture_layout, load_checkpoint, load_model, override
from dagr_lite.eval.operating import OperatingPoint
from dagr_lite.eval.score import detections_of, score_entries
from dagr_lite.nn.detector import Detector
from dagr_lite.nn.head import box_iou
from dagr_lite.progress import progress_bar
from dagr_lite.stream import StreamingDetector

# Boxes of frames k and k + 1 are the same hand when their IoU is at least this (after the best one-to-one match).
MATCH_IOU = 0.3
# A true box moved since the image when it overlaps every box of the image's frame by less than this.
MOVED_IOU = 0.5
RESULT_KEYS = ("ckpt", "model", "age_frames", "age_ms", "mAP", "AP50", "AP75", "num_images", "recall_moved",
               "recall_still", "num_moved", "num_still")


def match_boxes(a: np.ndarray, b: np.ndarray, min_iou: float = MATCH_IOU) -> np.ndarray | None:
    """The order of ``b`` that pairs each box of ``a`` with the same hand, or None.

    Boxes (xyxy) are paired one to one by the largest total IoU (Hungarian assignment); the
    frames match only when they hold as many boxes and every pair overlaps by ``min_iou``.
    """
    if len(a) != len(b):
        return None
    if len(a) == 0:
        return np.zeros(0, dtype=np.int64)
    iou = box_iou(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)).numpy()
    rows, cols = linear_sum_assignment(-iou)
    if np.any(iou[rows, cols] < min_iou):
        return None
    return cols[np.argsort(rows)]


def interpolate_boxes(a: np.ndarray, b: np.ndarray, fraction: float) -> np.ndarray:
    """Boxes a fraction of the way from frame k's ``a`` to frame k + 1's matched ``b``: ``(1 - f) a + f b``."""
    order = match_boxes(a, b)
    if order is None:
        raise ValueError("the boxes of the two frames do not match one to one")
    return ((1 - fraction) * np.asarray(a, np.float64) + fraction * np.asarray(b, np.float64)[order]).astype(np.float32)


def sweep_frames(dataset: EventEgoHands, first: int, between: int) -> list[tuple[int, int]]:
    """``(video number, k)`` of the label frames a sweep scores: ``k >= first``; with ``between``
    also a next frame whose boxes match frame k's one to one."""
    frames = []
    for v in range(len(dataset.videos)):
        for k in range(first, dataset.num_frames(v) - (1 if between else 0)):
            if between and match_boxes(dataset.boxes_of(v, k), dataset.boxes_of(v, k + 1)) is None:
                continue
            frames.append((v, k))
    return frames


def point_truth(dataset: EventEgoHands, v: int, k: int, fraction: float) -> tuple[np.ndarray, int]:
    """The boxes (xyxy) and the time (us) of a sweep point ``fraction`` of a frame interval after
    label frame ``k`` of video number ``v`` (boxes interpolated towards frame ``k + 1``'s)."""
    boxes = dataset.boxes_of(v, k)
    t_end = dataset.frame_time_us(v, k)
    if fraction:
        boxes = interpolate_boxes(boxes, dataset.boxes_of(v, k + 1), fraction)
        t_end += int(round(fraction * (dataset.frame_time_us(v, k + 1) - t_end)))
    return boxes, t_end


def streamed_detections(model: Detector, dataset: EventEgoHands, frames: list[tuple[int, int]], age: int,
                        fraction: float, *, conf_threshold: float, nms_threshold: float, chunk_us: int = 5_000,
                        progress: bool = True, desc: str = "streaming") -> list[tuple]:
    """What the streaming detector answers at one sweep point, fed as a camera feeds it.

    For each label frame, a new :class:`StreamingDetector` with the dataset's horizon and context
    is fed the stream's events in ``chunk_us`` pieces from well before the image (``window_us +
    graph_context_us + context_us`` and the longer of the two
    arrival filters' periods before it), the image of frame ``k - age`` at its time, the
    events up to the point's time, and then asked for detections at that time. Entries as
    :func:`~dagr_lite.eval.score.detections_of` gives them, in ``frames``' order.
    """
    entries = []
    height, width = dataset.image_size
    for v, k in progress_bar(frames, desc=desc, leave=False, disable=not progress):
        boxes, t_end = point_truth(dataset, v, k, fraction)
        image_frame = k - age
        t_image = dataset.frame_time_us(v, image_frame)
        stream = StreamingDetector(model, dataset.sample, OperatingPoint(score=conf_threshold, nms_iou=nms_threshold))
        t_begin = (min(t_image, t_end) - dataset.window_us - dataset.graph_context_us - dataset.context_us
                   - dataset.sample.filter_lead_us)
        events = dataset.events_of(v, max(t_begin, 0), t_end)
        edges = sorted({*range(t_begin, t_end, chunk_us), t_image, t_end})
        cuts = np.searchsorted(events["t"], edges, side="left")
        for t0, lo, hi in zip(edges[:-1], cuts[:-1], cuts[1:]):
            if t0 == t_image:
                stream.push_image(dataset.image_of(v, image_frame), t_image)
            stream.push_events(*(events[key][lo:hi] for key in ("x", "y", "t", "p")))
        if t_image == t_end:  # age 0: the image comes with the last events
            stream.push_image(dataset.image_of(v, image_frame), t_image)
        answer = stream.detect(t_end)
        entries.append((fmt.label_key(dataset.videos[v], k), height, width, np.asarray(boxes, np.float32),
                        answer["boxes"], answer["scores"]))
    return entries


class SweepSamples(Dataset):
    """The samples of one sweep point: image age ``age`` frames, asked for ``fraction`` of a frame
    interval after label frame ``k``, over the sweep's ``frames``."""

    def __init__(self, dataset: EventEgoHands, frames: list[tuple[int, int]], age: int, fraction: float, seed: int,
                 blank_image: bool = False):
        self.dataset, self.frames, self.age, self.fraction, self.seed = dataset, frames, age, fraction, seed
        self.blank_image = blank_image

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Sample:
        ds, (v, k) = self.dataset, self.frames[index]
        boxes, t_end = point_truth(ds, v, k, self.fraction)
        rng = np.random.default_rng([self.seed, index])
        sample = ds.sample_at(v, k, k - self.age, t_end, boxes, rng)
        if self.blank_image:  # an ablation: what the model makes of the events alone
            sample = sample.blank_frame()
        return sample


def moved_recall(entries: list[tuple], image_boxes: list[np.ndarray], score: float) -> dict:
    """The recall of true boxes that moved since the image and of those that did not.

    A true box moved when its IoU with every box of the image's frame (``image_boxes``, one array
    per entry) is below :data:`MOVED_IOU`; it is found when a detection of score ``score`` or more
    overlaps it by IoU 0.5 or more. Entries are :func:`~dagr_lite.eval.score.detections_of`'s.
    Returns ``recall_moved``, ``recall_still`` (None where there is no such box) and their counts.
    """
    found = {"moved": [0, 0], "still": [0, 0]}
    for (_, _, _, truth, boxes, scores), before in zip(entries, image_boxes, strict=True):
        if not len(truth):
            continue
        truth = torch.as_tensor(np.asarray(truth), dtype=torch.float64).reshape(-1, 4)
        before = torch.as_tensor(np.asarray(before), dtype=torch.float64).reshape(-1, 4)
        kept = torch.as_tensor(np.asarray(boxes)[np.asarray(scores) >= score], dtype=torch.float64).reshape(-1, 4)
        moved = (box_iou(truth, before).max(dim=1).values < MOVED_IOU if len(before)
                 else torch.ones(len(truth), dtype=torch.bool))
        hit = box_iou(truth, kept).max(dim=1).values >= 0.5 if len(kept) else torch.zeros(len(truth), dtype=torch.bool)
        for kind, mask in (("moved", moved), ("still", ~moved)):
            found[kind][0] += int(hit[mask].sum())
            found[kind][1] += int(mask.sum())
    return {**{f"recall_{kind}": (hits / count if count else None) for kind, (hits, count) in found.items()},
            **{f"num_{kind}": count for kind, (_, count) in found.items()}}


def sweep_points(ages: list[int], between: int) -> list[tuple[int, float]]:
    """``(age, fraction)`` of every point: each age, and with ``between`` its in-between times."""
    steps = max(1, between)
    return [(age, j / steps) for age in ages for j in range(steps)]


def score_point(cfg: DictConfig, model, dataset: EventEgoHands, frames: list[tuple[int, int]], age: int,
                fraction: float, device: torch.device, score: float, entries_out: dict | None = None
                ) -> dict[str, float]:
    """COCO metrics of ``model`` at one sweep point: of the batch model, or with ``cfg.stream`` of
    what the streaming detector answers (:func:`streamed_detections`); and :func:`moved_recall`
    of its detections of ``score`` or more (the checkpoint's operating point). ``entries_out``:
    a dict that receives the point's detections (:func:`~dagr_lite.eval.score.detections_of`'s
    entries) under ``(age, fraction)``."""
    desc = f"age {age + fraction:g} frames"
    if cfg.stream:
        entries = streamed_detections(model, dataset, frames, age, fraction, conf_threshold=cfg.eval.conf_threshold,
                                      nms_threshold=cfg.eval.nms_threshold, desc=desc + ", streaming")
    else:
        samples = SweepSamples(dataset, frames, age, fraction, cfg.seed, blank_image=cfg.blank_image)
        loader = make_loader(samples, batch_size=cfg.loader.batch_size, num_workers=cfg.loader.num_workers,
                             graph=model.graph_spec, worker_nice=cfg.loader.worker_nice)
        entries = detections_of(model, loader, device, conf_threshold=cfg.eval.conf_threshold,
                                nms_threshold=cfg.eval.nms_threshold, desc=desc)
    if entries_out is not None:
        entries_out[(age, fraction)] = entries
    metrics, evaluator = score_entries(entries, backend=cfg.eval.backend)
    image_boxes = [dataset.boxes_of(v, k - age) for v, k in frames]
    return {"mAP": metrics["mAP"], "AP50": metrics["AP50"], "AP75": metrics["AP75"],
            "num_images": len(evaluator.images), **moved_recall(entries, image_boxes, score)}


# What a sample is, besides its image age (the sweep's own): the checkpoint's unless given.
OVERRIDABLE = SampleSpec.keys()


def checkpoint_data(cfg: DictConfig, checkpoint: Checkpoint) -> tuple[dict, dict]:
    """The data settings a checkpoint is swept with (its own, ``data.*`` overriding them) and the
    overrides; a bad value, or one that changes the model's input picture's channels, is refused."""
    overrides: dict = {}
    data = checkpoint.sample_settings
    data.update({key: override("data", key, data[key], cfg.data.get(key), overrides) for key in OVERRIDABLE})
    SampleSpec.from_dict(data)  # the values, before the channels they make
    check_picture_layout(checkpoint.path, checkpoint.sample_settings, data)
    return data, overrides


def sweep_checkpoint(cfg: DictConfig, checkpoint: Checkpoint, frames: list[tuple[int, int]] | None,
                     device: torch.device, entries_out: dict | None = None
                     ) -> tuple[list[dict], list[tuple[int, int]], dict]:
    """The rows of one checkpoint at every sweep point, with its own data settings (image age
    aside) unless ``data.*`` overrides them; the frames are found on first use and shared by
    every later checkpoint. Also returns the overrides (``{"data.key": {"checkpoint", "used"}}``).
    ``entries_out``: see :func:`score_point`."""
    detector, path = checkpoint.detector, str(checkpoint.path)
    data, overrides = checkpoint_data(cfg, checkpoint)
    run_cfg = OmegaConf.merge(cfg, {"data": data})
    largest = max(cfg.ages)
    dataset = build_dataset(run_cfg, cfg.split, train=False, with_image=detector.use_image, image_age=largest,
                            first_frame=largest)
    if frames is None:
        frames = sweep_frames(dataset, largest, cfg.between)
        if not frames:
            lengths = [dataset.num_frames(v) for v in range(len(dataset.videos))]
            paired = " whose boxes pair with frame k + 1's (between)" if cfg.between else ""
            held = f"its videos have {min(lengths)} to {max(lengths)} frames" if lengths else "it has no video"
            raise ConfigError(f"no label frame k >= {largest} (the largest of ages={list(cfg.ages)}){paired} in split "
                              f"{cfg.split}: {held}; give smaller ages")
    model = load_model(checkpoint, detector, dataset.image_size).to(device)
    name = (checkpoint.model_name + (" (grey image)" if cfg.blank_image else "")
            + (" (streaming)" if cfg.stream else ""))
    changed = "".join(f", {key}={value['used']} (trained with {value['checkpoint']})" for key, value in overrides.items())
    print(f"{path}: {name}, {len(frames)} label frames of {cfg.split}{changed}", flush=True)
    rows = [{"ckpt": str(path), "model": name, "age_frames": age if not fraction else round(age + fraction, 6),
             "age_ms": round(1000 * (age + fraction) / cfg.dataset.fps, 3),
             **score_point(run_cfg, model, dataset, frames, age, fraction, device, checkpoint.operating.score,
                           entries_out)}
            for age, fraction in sweep_points(list(cfg.ages), cfg.between)]
    return rows, frames, overrides


def check_sweep(cfg: DictConfig) -> None:
    ages = cfg.ages
    if not isinstance(ages, ListConfig) or not ages or not all(isinstance(a, int) and a >= 0 for a in ages):
        raise ConfigError(f"ages must be a non-empty list of integers >= 0 (frames), got {ages!r}")
    if not isinstance(cfg.between, int) or cfg.between < 0:
        raise ConfigError(f"between must be an integer >= 0 (0: label frames only), got {cfg.between!r}")
    if not isinstance(cfg.blank_image, bool):
        raise ConfigError(f"blank_image must be true or false, got {cfg.blank_image!r}")
    if not isinstance(cfg.stream, bool):
        raise ConfigError(f"stream must be true or false, got {cfg.stream!r}")
    if cfg.stream and cfg.blank_image:
        raise ConfigError("stream=true scores what a camera's stream gives; blank_image=true is a batch ablation: "
                          "give one of them")
    if isinstance(cfg.ckpt, str) and cfg.ckpt:  # one checkpoint needs no brackets
        cfg.ckpt = [cfg.ckpt]
    if not isinstance(cfg.ckpt, ListConfig) or not cfg.ckpt:
        raise ConfigError(f"ckpt must be a checkpoint or a list of them, e.g. ckpt=[a.pt,b.pt], got {cfg.ckpt!r}")
    for path in cfg.ckpt:
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path}: checkpoint file is missing")
    if cfg.out is not None and (Path(cfg.out) / "sweep.json").exists():
        raise FileExistsError(f"{cfg.out}: holds an earlier sweep (sweep.json); choose a new out")


def sweep(cfg: DictConfig) -> dict:
    """Score every checkpoint at every point; write ``sweep.json``, ``sweep.csv``, ``sweep.png``."""
    cfg = resolve_config(cfg)
    check_sweep(cfg)
    out = Path(cfg.out) if cfg.out is not None else run_folder(cfg, "sweep", make=False)
    device = resolve_device(cfg.device)
    rows, frames, overrides = [], None, {}
    checkpoints = [load_checkpoint(path) for path in cfg.ckpt]  # every one, before any is scored
    for checkpoint in checkpoints:  # and the data settings of every one
        checkpoint_data(cfg, checkpoint)
    for checkpoint in checkpoints:
        ckpt_rows, frames, changed = sweep_checkpoint(cfg, checkpoint, frames, device)
        rows += ckpt_rows
        if changed:
            overrides[str(checkpoint.path)] = changed
    out.mkdir(parents=True, exist_ok=True)  # only once there is something to write
    write_results(out, rows, split=cfg.split, between=cfg.between, blank_image=cfg.blank_image, overrides=overrides,
                  stream=cfg.stream)
    print(format_table(rows), flush=True)
    print(f"wrote {out / 'sweep.json'}, sweep.csv and sweep.png", flush=True)
    return {"results": rows, "frames": frames, "out": out, "overrides": overrides}


def write_results(out: Path, rows: list[dict], *, split: str, between: int, blank_image: bool,
                  overrides: dict | None = None, stream: bool = False) -> None:
    """``overrides``: per checkpoint, the data settings given on the command line instead of its own;
    ``stream``: the rows score the streaming detector's answers."""
    summary = {"split": split, "between": between, "blank_image": blank_image, "stream": stream,
               "overrides": overrides or {}, "results": rows}
    # sweep.json, which marks a finished sweep (a rerun into out is refused), comes last: a sweep that
    # fails on the plot or the table can be run again into the same folder
    plot_sweep(rows, out / "sweep.png", between=between)
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=RESULT_KEYS)
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomically(out / "sweep.csv", table.getvalue())
    write_text_atomically(out / "sweep.json", json.dumps(summary, indent=1))


def checkpoint_name(ckpt: str) -> str:
    """A checkpoint's short name: its run's folder and file (``run/best.pt``), so two runs' ``best.pt`` differ."""
    path = Path(ckpt)
    run = path.parent.parent.name if path.parent.name == "checkpoints" else path.parent.name
    return f"{run}/{path.name}" if run else path.name


def format_table(rows: list[dict]) -> str:
    """AP50, mAP and the recall of moved and of still hands per checkpoint (rows) and image age (columns)."""
    ages = sorted({r["age_ms"] for r in rows})
    lines = []
    for metric, title in (("AP50", "AP50"), ("mAP", "mAP"), ("recall_moved", "moved"), ("recall_still", "still")):
        lines.append(f"{title:<10s} {'checkpoint':<40s} " + " ".join(f"{a:7.1f}" for a in ages) + "   (image age, ms)")
        for ckpt in dict.fromkeys(r["ckpt"] for r in rows):
            mine = {r["age_ms"]: r for r in rows if r["ckpt"] == ckpt}
            name = f"{mine[ages[0]]['model']} {checkpoint_name(ckpt)}"
            lines.append(f"{'':<10s} {name[-40:]:<40s} "
                         + " ".join("      -" if mine[a].get(metric) is None else f"{mine[a][metric]:7.3f}" for a in ages))
    lines.append("moved / still: recall of the hands that moved since the image (IoU < 0.5 with every box of its frame) "
                 "/ did not, at each checkpoint's operating point")
    return "\n".join(lines)


def curve_points(rows: list[dict], metric: str, between: int) -> tuple[list[float], list[float]]:
    """One checkpoint's ``metric`` against the image's age in milliseconds, for a plot: rows in order
    of age, a metric of None (no such hand) as NaN, and with ``between`` a NaN between points more
    than one in-between step apart (ages not next to each other), so the line is broken where
    nothing was measured rather than drawn straight across it."""
    xs: list[float] = []
    ys: list[float] = []
    previous = None
    for r in sorted(rows, key=lambda r: r["age_ms"]):
        if between and previous is not None and r["age_frames"] - previous > 1.5 / between:  # (ages rounded)
            xs.append(math.nan)
            ys.append(math.nan)
        xs.append(r["age_ms"])
        ys.append(math.nan if r.get(metric) is None else max(r[metric], 0.0))
        previous = r["age_frames"]
    return xs, ys


def plot_sweep(rows: list[dict], path: Path, *, between: int) -> None:
    """mAP and AP50 against the image's age in milliseconds, one line per checkpoint, and the recall
    of the hands that moved since the image (solid) and of those that did not (dashed), each
    checkpoint in its own colour."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), sharex=True)
    marker = "." if between else "o"
    for ckpt in dict.fromkeys(r["ckpt"] for r in rows):
        mine = [r for r in rows if r["ckpt"] == ckpt]
        label = f"{mine[0]['model']} ({checkpoint_name(ckpt)})"
        for ax, metric in zip(axes, ("mAP", "AP50")):
            (line,) = ax.plot(*curve_points(mine, metric, between), marker=marker, label=label)
        for metric, style in (("recall_moved", "-"), ("recall_still", "--")):
            axes[2].plot(*curve_points(mine, metric, between), style, marker=marker, color=line.get_color())
    ages = sorted({r["age_ms"] for r in rows})
    titles = ("mAP (AP@[.5:.95])", "AP50", "recall at the operating point:\nmoved since the image (solid), still (dashed)")
    for ax, metric, title in zip(axes, ("mAP", "AP50", None), titles):
        if not between and len(ages) <= 12:  # ticks at the ages measured, in whole milliseconds
            ax.set_xticks(ages, [f"{age:.0f}" for age in ages])
        ax.set_xlabel("image age: time since the image (ms)")
        ax.set_ylabel(title if metric else "recall")
        if metric:
            ax.set_ylim(0, min(1.0, 1.15 * max(max(r[metric] for r in rows), 0.05)))
        else:
            ax.set_title(title, fontsize=9)
            ax.set_ylim(0, 1.05)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 3), fontsize=8, frameon=False)
    title = "detection against image age" + (f" (every 1/{between} of a frame interval)" if between else "")
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


main = hydra_command("sweep", sweep)


if __name__ == "__main__":
    main()
