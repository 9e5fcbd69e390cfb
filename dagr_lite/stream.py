"""The streaming detector: detections at any moment, equal to the batch model on the same sample.

Images arrive at the camera's rate, events continuously; :meth:`StreamingDetector.detect`
answers at any time. The answer equals the batch model (:class:`~dagr_lite.nn.detector.Detector`)
run on the sample of that moment, the sample training and evaluation read
(:func:`~dagr_lite.data.spec.sample_start_us`, docs/design.md, "One sample"):

- every model reads the events of ``[t - window_us, t]`` (a horizon);
- a hybrid reads the latest image, and no event from before ``image time - context_us``;
- with ``refractory_us`` > 0, an event whose pixel had one less than that long before it is
  dropped on arrival; with ``support_us`` > 0, one whose 8 neighbouring pixels had none less than
  that long before it (:func:`~dagr_lite.data.dataset.arrival_keep`);
- a carry branch reads the picture of every event since the image (with ``carry_confirm_us``,
  also of those a neighbouring pixel confirms; with ``carry_spans_us`` and ``carry_onset``, also
  each pixel's counts per span of time since the image and its first event; with
  ``carry_align_us``, also the frame moved by the camera's motion since it:
  :class:`~dagr_lite.data.dataset.CarryPicture`).

Work per update: new events get their incoming edges from the streaming graph builder, the
first GCN stage computes the new nodes only (reading the cached features of older nodes; a
node never changes once computed, as the graph is causal). While no event of a hybrid's
sample has left the horizon, its first pooled cells take the new nodes in (max and mean are
updated, never recomputed, as the cells only gain members). The pooled stages are then run in
full (the pooled graph has a few hundred cells). Without ``late_query`` the recency maps, the
fusion and the head run over every cell (the query time reaches every cell through the recency
maps and the image's age); with it the head's towers are rerun only at the cells whose event
maps changed and the cells their 3x3 layers reach (:class:`~dagr_lite.nn.head.TowerCache`), and the query time enters
after the towers, in 1x1 layers over every cell. Image features (and a ``late_query`` hybrid's
image towers) are computed once per image. Once
events leave the horizon, the nodes near its start, whose edges or whose neighbours'
in-degrees reached the events that left, are recomputed from the events of the horizon (a
prefix of ``(event_blocks + 1) * radius / time_scale`` microseconds, ``time_scale`` being beta as
the graph applies it), and the pooled graph is
rebuilt from the horizon's nodes. With a sample's graph context of at least that reach
(``graph_context_us``), no node is ever recomputed: an answer pools the cached nodes of its horizon.
"""
from __future__ import annotations

import copy
import math
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from dagr_lite.errors import UserError
from dagr_lite.data.dataset import CarryPicture, arrival_keep, carry_channels, sample_start_us
from dagr_lite.data.spec import SampleSpec
from dagr_lite.eval.operating import OperatingPoint
from dagr_lite.graph.pool import PooledGraph, add_members, latest_times, recency_cells, recency_since
from dagr_lite.graph.sparse import compiled_for
from dagr_lite.graph.streaming import StreamingGraph, edges_after
from dagr_lite.nn.blocks import fold_batch_norms, pack_convolutions
from dagr_lite.nn.detector import Detector, DetectorConfig
from dagr_lite.nn.head import postprocess

# Before the first image, how much of the event stream is kept for its context (an image may be
# stamped this long before the latest event).
MAX_IMAGE_DELAY_US = 1_000_000
# An events-only stream moves its time origin forward after this long, so that float32 event
# times stay whole microseconds (2^24 us is where float32 stops holding every integer).
REORIGIN_US = 1 << 23


class _Rows:
    """A tensor (or numpy array) that grows along its first axis, with amortised doubling."""

    def __init__(self, like: torch.Tensor | np.ndarray):
        self.data = like[:0]
        self.n = 0

    @property
    def view(self):
        return self.data[: self.n]

    def extend(self, rows) -> None:
        need = self.n + len(rows)
        if need > len(self.data):
            size = max(need, 2 * len(self.data), 256)
            if isinstance(rows, torch.Tensor):
                grown = rows.new_empty((size, *rows.shape[1:]))
            else:
                grown = np.empty((size, *rows.shape[1:]), dtype=rows.dtype)
            grown[: self.n] = self.data[: self.n]
            self.data = grown
        self.data[self.n: need] = rows
        self.n = need

    def drop_front(self, k: int) -> None:
        """Forget the first ``k`` rows."""
        if k:
            self.data = self.data[k: self.n].clone() if isinstance(self.data, torch.Tensor) else \
                self.data[k: self.n].copy()
            self.n -= k


class _Cells:
    """The first pooled graph of a hybrid's nodes, kept up to date as nodes arrive (never leave).

    Mirrors :func:`~dagr_lite.graph.pool.voxel_max_pool` over all nodes so far: a cell's
    features are the running max of its members', its position their running sum over the
    count, and its edges the set of cell pairs of the member edges.
    """

    def __init__(self, height: int, width: int, stride: int, channels: int, dtype, device):
        self.stride, self.cols = stride, math.ceil(width / stride)
        self.size = math.ceil(height / stride) * self.cols
        self.x = torch.full((self.size, channels), -math.inf, dtype=dtype, device=device)
        self.pos_sum = torch.zeros((self.size, 3), dtype=dtype, device=device)
        self.count = torch.zeros(self.size, dtype=torch.int64, device=device)
        self.seen = torch.zeros(self.size * self.size, dtype=torch.bool, device=device)  # by dst * size + src
        self.keys = torch.zeros(0, dtype=torch.int64, device=device)  # sorted edge keys

    def cell_of(self, pos: torch.Tensor) -> torch.Tensor:
        col = torch.div(pos[:, 0], self.stride, rounding_mode="floor").to(torch.int64)
        row = torch.div(pos[:, 1], self.stride, rounding_mode="floor").to(torch.int64)
        return row * self.cols + col

    def add(self, x: torch.Tensor, pos: torch.Tensor, cell: torch.Tensor, edge_cells: torch.Tensor) -> None:
        """New members ``x (M, C)`` at ``pos (M, 3)`` in cells ``cell (M,)``, and the cells
        ``(2, E)`` (source, destination) of their incoming edges."""
        if compiled_for(x):  # one compiled pass, the same cells
            keys = torch.from_numpy(add_members(self.x.numpy(), self.pos_sum.numpy(), self.count.numpy(),
                                                self.seen.numpy(), x.contiguous().numpy(), pos.contiguous().numpy(),
                                                cell.contiguous().numpy(), edge_cells[0].contiguous().numpy(),
                                                edge_cells[1].contiguous().numpy()))
            if len(keys):
                self.keys = torch.sort(torch.cat([self.keys, keys])).values
            return
        self.x.scatter_reduce_(0, cell[:, None].expand(-1, x.shape[1]), x, reduce="amax")
        self.pos_sum.index_add_(0, cell, pos)
        self.count += torch.bincount(cell, minlength=self.size)
        keys = torch.unique(edge_cells[1] * self.size + edge_cells[0])
        keys = keys[~self.seen[keys]]
        if len(keys):
            self.seen[keys] = True
            self.keys = torch.sort(torch.cat([self.keys, keys])).values

    def graph(self) -> PooledGraph:
        """The pooled graph of the occupied cells, ordered as :func:`voxel_max_pool` orders them."""
        occupied = torch.nonzero(self.count).flatten()  # (C,) ascending: by (row, column)
        local = torch.full((self.size,), -1, dtype=torch.int64, device=occupied.device)
        local[occupied] = torch.arange(len(occupied), device=occupied.device)
        dst, src = torch.div(self.keys, self.size, rounding_mode="floor"), self.keys % self.size
        counts = self.count[occupied].to(self.pos_sum.dtype)
        return PooledGraph(x=self.x[occupied], pos=self.pos_sum[occupied] / counts[:, None],
                           batch=torch.zeros_like(occupied),
                           cell=torch.stack([torch.div(occupied, self.cols, rounding_mode="floor"),
                                             occupied % self.cols], dim=1),
                           edge_index=torch.stack([local[src], local[dst]]), cluster=occupied.new_zeros(0))


class _Segment:
    """Everything computed since a time origin: one image's events for a hybrid, or a stretch of an
    events-only stream. Node ids are global (the streaming graph's); row ``i`` of the buffers is
    node ``base + i``."""

    def __init__(self, detector: "StreamingDetector", origin_us: float):
        model, branch = detector.net, detector.net.events
        spec = model.graph_spec
        self.origin_us, self.base = origin_us, 0
        self.first_us = origin_us  # the earliest event time of the segment's sample
        self.graph = StreamingGraph(spec.radius, spec.max_neighbors, workers=1)
        like = torch.zeros(0, dtype=detector.dtype, device=detector.device)
        self.events = _Rows(like.new_zeros((0, 4)))  # x, y, t - origin, p
        self.t_abs = _Rows(np.zeros(0))
        self.pos = _Rows(like.new_zeros((0, 3)))
        self.exact_pos = _Rows(torch.zeros((0, 3), dtype=torch.float64, device=detector.device))  # for the geometry
        # the input of each first-stage block, then its output
        self.h = [_Rows(like.new_zeros((0, width))) for width in branch.first_stage_widths]
        self.in_degree = _Rows(torch.zeros(0, dtype=torch.int64, device=detector.device))
        self.edges = _Rows(torch.zeros((0, 2), dtype=torch.int64, device=detector.device))  # (src, dst), global ids
        self.cell = _Rows(torch.zeros(0, dtype=torch.int64, device=detector.device))  # first pooled cell, hybrid
        # A hybrid's first pooled cells over every node of the segment: valid until a node leaves the horizon.
        self.cells = (_Cells(model.cfg.height, model.cfg.width, branch.pool_stride, branch.first_stage_widths[-1],
                             detector.dtype, detector.device) if detector.hybrid else None)
        self.latest = [like.new_full((2 * h * w,), -math.inf) for h, w in detector.map_sizes]
        self.maps: tuple[int, list[torch.Tensor]] | None = None  # a hybrid's event maps, with the node count they saw
        # The head over the segment's latest event maps (models whose query maps enter after the towers).
        self.towers = model.tower_cache() if model.cfg.late_query else None


def check_streamable(detector: DetectorConfig, sample: SampleSpec, where: str = "") -> None:
    """Refuse (:class:`~dagr_lite.errors.UserError`, prefixed by ``where``) a model the streaming detector cannot run."""
    if not detector.use_events:
        raise UserError(f"{where}the streaming detector needs a model with an event branch (use_events true)")
    if sample.carry_picture and not detector.carry_width:
        raise UserError(f"{where}this model's image branch reads a picture of the events since the image beside the "
                         "camera frame (data.carry_picture without model.carry_width); the streaming detector runs "
                         "such a picture through a carry branch only, whose maps join at the fusion")
    made = carry_channels(sample.carry_recent_us, sample.carry_confirm_us, sample.carry_align_us,
                          sample.carry_spans_us, sample.carry_onset)
    if detector.carry_width and made != detector.carry_channels:
        raise UserError(f"{where}this model's carry branch reads pictures of {detector.carry_channels} channels, but "
                         f"data.carry_recent_us={sample.carry_recent_us}, data.carry_confirm_us="
                         f"{sample.carry_confirm_us}, data.carry_align_us={sample.carry_align_us}, "
                         f"data.carry_spans_us={list(sample.carry_spans_us)} and data.carry_onset="
                         f"{sample.carry_onset} make pictures of {made} (three, one more with a recent window, three "
                         "more with confirmed events, three more with the moved frame, one per span, one with the "
                         "onset)")
    if sample.event_picture:
        raise UserError(f"{where}this model reads a picture of events in place of the camera frame "
                         "(data.event_picture, the dense peer of benchmarks/dense_peer.py); the streaming "
                         "detector runs models that read camera frames and events")


class StreamingDetector:
    """A detector fed by a stream: ``push_image``, ``push_events``, then ``detect`` at any moment.

    Args:
        model: a :class:`Detector` with an event branch (hybrid or events-only); it is put in
            evaluation mode.
        sample: the events it reads (:class:`~dagr_lite.data.spec.SampleSpec`): those of the horizon
            ``[t - window_us, t]``, for a hybrid none from before ``image time - context_us``, less
            those a refractory period or the background-activity filter drops, decided as they arrive.
        operating: the score threshold and NMS IoU of its answers
            (:class:`~dagr_lite.eval.operating.OperatingPoint`).
        packed: the answering copy's convolutions packed for oneDNN, with their activations
            (:func:`~dagr_lite.nn.blocks.pack_convolutions`; float32 on a CPU; 1.14x the real-time
            factor). Its sums run in another order than the batch model's: the raw outputs agree
            to 1e-5, and detections whose scores tie to 1e-6 can come in another order, or another
            one of them be cut at the hundredth (docs/design.md, "The streaming detector"). False:
            torch's own convolutions.

    ``model`` stays the model given, which the answers equal; ``net`` is the copy that answers, each
    convolution's batch norm folded into it (:func:`~dagr_lite.nn.blocks.fold_batch_norms`: equal up
    to rounding, one operation less per block) and, with ``packed``, each convolution's weight laid out
    once for oneDNN with the SiLU after it applied in the same call (equal up to rounding). Its state
    is made and changed in inference mode.

    Times are microseconds on the stream's clock. Events come as numpy arrays sorted by time;
    ``x``, ``y`` in pixels of the model's frame size, ``p`` in {0, 1}. Bad input raises
    ``ValueError`` naming what was wrong and leaves the detector as it was.
    """

    def __init__(self, model: Detector, sample: SampleSpec, operating: OperatingPoint, packed: bool = True):
        check_streamable(model.cfg, sample)
        self.model = model.eval()  # the model given, which the answers equal
        # What answers: a copy with each convolution's batch norm folded into it (one operation less per block)
        # and, with packed, its convolutions packed for oneDNN with their activations (float32 on a CPU). A late-query head
        # computes its blocks' rows by hand (TowerCache), so its activations stay modules.
        self.net = fold_batch_norms(copy.deepcopy(model))
        if not model.cfg.late_query:  # each stride's two towers as one, its predictions as one (nn.head)
            for head in (self.net.head, self.net.event_head):
                if head is not None:
                    head.merge_branches()
        for branch in (self.net.image, self.net.carry):  # the pixels' scaling folded into a patch stem
            if branch is not None and branch.stem_kind == "patch":
                branch.read_raw_pixels()
        self._split_carry = self.net.split_carry_frame()  # the frame's share of the carry stem once a frame
        self._carry_frame_part = None
        self._split_fusion = self.net.split_fusion()  # the image's share of the fusion once an image
        if packed:
            self.net = pack_convolutions(self.net, fuse_activations=not model.cfg.late_query)
        parameter = next(model.parameters())
        self.dtype, self.device = parameter.dtype, parameter.device
        self.hybrid = model.image is not None
        self.sample, self.operating = sample, operating
        self.context_us, self.window_us, self.refractory_us = sample.context_us, sample.window_us, sample.refractory_us
        self.support_us = sample.support_us
        # How long before an image its sample may read: the context, or the confirmation of a carry picture.
        self._lead_us = max(self.context_us, sample.carry_confirm_us if model.carry is not None else 0)
        self.height, self.width = model.cfg.height, model.cfg.width
        self.map_sizes = [(math.ceil(self.height / s), math.ceil(self.width / s)) for s in model.strides]
        spec = model.graph_spec
        # How far back in time a node's features reach through the first stage's edges and degrees.
        self.reach_us = (len(model.events.first_stage) + 1) * spec.radius / spec.time_scale
        self.radius_us = spec.radius / spec.time_scale  # how far back in time an event's edges reach
        self.graph_context_us = sample.graph_context_us
        if 0 < self.graph_context_us < self.reach_us:
            raise UserError(f"sample graph_context_us={self.graph_context_us} is shorter than the "
                            f"{self.reach_us:g} us a node's features reach back ((event_blocks + 1) * radius / beta, "
                            "beta as the graph rounds it): the streaming detector answers exactly with 0 or at "
                            "least that")
        self.timings: dict[str, float] | None = None  # a dict: seconds spent in each part, summed (profiling)
        self.reset()

    @classmethod
    def from_checkpoint(cls, path: str | Path, device: str | torch.device = "cpu",
                        model_size: tuple[int, int] | None = None, score: float | None = None,
                        nms_iou: float | None = None) -> "StreamingDetector":
        """The EMA weights of a training checkpoint, on the sample it was trained with, answering
        at its operating point (:class:`~dagr_lite.eval.operating.OperatingPoint`: chosen on the
        validation split; ``score``, ``nms_iou``: given by name instead).

        ``model_size = (width, height)`` runs the weights at another input size: they do not depend
        on it (convolutions, and node coordinates normalised by the input's size), while the graph's
        radius stays in pixels, so accuracy at another size is for a measurement to say."""
        from dagr_lite.engine.checkpoint import at_model_size, load_checkpoint

        checkpoint = load_checkpoint(path)
        detector = checkpoint.detector
        if model_size is not None:  # as evaluate.py model_size=data runs it
            detector = at_model_size("data", detector, (int(model_size[1]), int(model_size[0])), {})
        check_streamable(detector, checkpoint.sample, f"{path}: ")
        operating = checkpoint.operating.with_overrides(score=score, nms_iou=nms_iou)
        return cls(checkpoint.model(detector).to(device), checkpoint.sample, operating)

    @property
    def ready(self) -> bool:
        """Whether :meth:`detect` can answer: always for events-only, after an image for a hybrid."""
        return not self.hybrid or self._t_image is not None

    @property
    def last_event_us(self) -> float:
        """The time of the latest event pushed (-inf before any): later pushes may not be earlier."""
        return self._last_t

    def reset(self) -> None:
        """Forget every image and event."""
        self._log = {key: _Rows(np.zeros(0)) for key in ("x", "y", "t", "p")}  # raw events not yet dropped
        self._done = 0  # events of the log already in the segment
        self._last_t = -math.inf
        self._pixel_last = np.full(self.height * self.width, -math.inf) if self.refractory_us else None
        self._support_last = np.full(self.height * self.width, -math.inf) if self.support_us else None
        self._kept_from = -math.inf  # the log holds every event since this time
        self._image = None  # (image maps, node maps, their sampler) of the latest image
        self._fusion_image = None  # the image's share of each stride's fusion (split_fusion)
        self._t_image: float | None = None
        self._frame: np.ndarray | None = None  # the latest image's pixels (a carry branch with carry_frame reads them)
        self._carry: CarryPicture | None = None  # a carry branch's picture of the events since the image
        self._segment: _Segment | None = None

    def warm_up(self, seed: int = 0) -> float:
        """Run the detector once over made-up input (a grey image, 3 horizons of random events in
        5 ms updates, so that events also leave the horizon), then :meth:`reset`; returns the seconds
        it took. The compiled kernels are compiled (or read from numba's cache) and torch's first
        calls made here, not in the first answers of a stream whose latency is measured."""
        tic, timings = time.perf_counter(), self.timings
        self.timings = None  # a profile's parts count the stream's answers, not these
        rng = np.random.default_rng(seed)
        span = 3 * self.window_us
        count = int(max(2000, 60 * span / 1000))  # about 60k events/s
        t = np.sort(rng.uniform(0, span, count)).astype(np.int64)
        x, y = rng.integers(0, self.width, count), rng.integers(0, self.height, count)
        p = rng.integers(0, 2, count)
        if self.hybrid:
            self.push_image(np.full((self.height, self.width, 3), 128, np.uint8), 0)
        for stop in np.arange(5_000, span + 5_000, 5_000):
            part = slice(int(np.searchsorted(t, stop - 5_000)), int(np.searchsorted(t, stop)))
            self.push_events(x[part], y[part], t[part], p[part])
            self.detect(float(stop))
        self.reset()
        self.timings = timings
        return time.perf_counter() - tic

    @property
    def origin_us(self) -> float | None:
        """The time event times count from in the model (a hybrid's image time; None before any)."""
        with torch.inference_mode():
            self._ingest()
        return None if self._segment is None else self._segment.origin_us

    # ---------------------------------------------------------------- input
    def push_image(self, image: np.ndarray, t_us: float) -> None:
        """A new image ``(H, W, 3)`` uint8 taken at ``t_us``; the hybrid restarts from it.
        A model without an image branch ignores images."""
        image = np.asarray(image)
        if image.shape != (self.height, self.width, 3) or image.dtype != np.uint8:
            raise UserError(f"image must be ({self.height}, {self.width}, 3) uint8 (the model's frame size), "
                             f"got {image.shape} {image.dtype}")
        t_us = float(t_us)
        if not math.isfinite(t_us):
            raise UserError(f"image time must be finite, got {t_us}")
        if self._t_image is not None and t_us < self._t_image:
            raise UserError(f"image at t={t_us:g} us is older than the previous image ({self._t_image:g} us)")
        if not self.hybrid:
            return
        needed_from = self.sample.graph_start_us(max(t_us, self._last_t), t_us)
        # A carry picture also reads every event since the image (and those that confirm them, before it).
        carry = CarryPicture(self.height, self.width, t_us, self.sample.carry_recent_us, self.sample.carry_confirm_us,
                             self.sample.carry_align_us, image, self.sample.carry_spans_us,
                             self.sample.carry_onset) if self.model.carry is not None else None
        read_from = needed_from if carry is None else min(needed_from, carry.reads_from_us)
        if read_from < self._kept_from:
            raise UserError(f"image at t={t_us:g} us needs the events from {read_from:g} us, but "
                             f"only those since {self._kept_from:g} us are kept (an image may be at most "
                             f"{MAX_IMAGE_DELAY_US} us older than the latest event)")
        with torch.inference_mode():  # every tensor of the stream's state is made and changed in inference mode
            with self._part("image features"):
                image_maps = self.net.frame_maps(self._pixels(image))
                node_maps = self.net.node_maps(image_maps)
                self._image = (image_maps, node_maps, self.net.node_sampler(node_maps))  # one sampler an image
                if self._split_carry:
                    self._carry_frame_part = self.net.carry_frame_part(self._pixels(image))
                if self._split_fusion:
                    self._fusion_image = self.net.fusion_image_part(image_maps)
            self._t_image, self._frame = t_us, image
            self._carry = carry  # the picture restarts from the logged events since the image
            self._add_to_carry(*(self._log[key].view for key in ("x", "y", "t", "p")))
            # Events older than the horizon of the earliest answer left to give are not read; the log keeps
            # those a later image's sample may read (its context, its carry picture's confirmation).
            self._start_segment(t_us, needed_from, keep_from_us=t_us - self._lead_us)

    def push_events(self, x, y, t, p) -> None:
        """Events sorted by ``t`` (any number, including 0), not earlier than any pushed before."""
        arrays = {"x": np.asarray(x), "y": np.asarray(y), "t": np.asarray(t), "p": np.asarray(p)}
        for name, values in arrays.items():
            if values.ndim != 1:
                raise UserError(f"events {name} must be a 1-D array, got shape {values.shape}")
            if values.dtype.kind not in "iuf" and len(values):
                raise UserError(f"events {name} must be numeric, got dtype {values.dtype}")
        lengths = {name: len(values) for name, values in arrays.items()}
        if len(set(lengths.values())) != 1:
            raise UserError(f"events x, y, t, p must have the same length, got {lengths}")
        if not lengths["t"]:
            return
        x, y, t, p = (arrays[k].astype(np.float64) for k in ("x", "y", "t", "p"))
        if not np.all(np.isfinite(t)):
            raise UserError("events t holds non-finite values")
        if np.any(np.diff(t) < 0):
            i = int(np.flatnonzero(np.diff(t) < 0)[0])
            raise UserError(f"events must be sorted by t: t[{i + 1}]={t[i + 1]:g} < t[{i}]={t[i]:g}")
        if t[0] < self._last_t:
            raise UserError(f"events must not be older than those pushed before: t[0]={t[0]:g} us < "
                             f"{self._last_t:g} us")
        for name, values, size in (("x", x, self.width), ("y", y, self.height)):
            bad = ~((values >= 0) & (values < size))
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise UserError(f"events {name} must lie in [0, {size}) (the sensor), got {name}[{i}]={values[i]:g}")
        if not np.all((p == 0) | (p == 1)):
            i = int(np.flatnonzero((p != 0) & (p != 1))[0])
            raise UserError(f"events p must be 0 or 1, got p[{i}]={p[i]:g}")
        last_t = float(t[-1])
        if self.sample.filter_lead_us:
            keep = arrival_keep(x, y, t, refractory_us=self.refractory_us, support_us=self.support_us,
                                width=self.width, height=self.height, pixel_last=self._pixel_last,
                                support_last=self._support_last)
            x, y, t, p = x[keep], y[keep], t[keep], p[keep]
        for name, values in (("x", x), ("y", y), ("t", t), ("p", p)):
            self._log[name].extend(values)
        self._last_t = last_t
        self._add_to_carry(x, y, t, p)

    # ---------------------------------------------------------------- output
    def detect(self, t_us: float | None = None) -> dict:
        """Detections at ``t_us`` (default: the latest event or image time), which may not be earlier
        than the latest event (or, for a hybrid, the image).

        Returns ``boxes (D, 4)`` xyxy pixels, ``scores (D,)``, ``labels (D,)`` (numpy) and ``t_us``.
        """
        latest = max(self._last_t, self._t_image if self._t_image is not None else -math.inf)
        if t_us is None:
            if not math.isfinite(latest):
                raise UserError("nothing was pushed yet: give detect a time")
            t_us = latest
        t_us = float(t_us)
        if not math.isfinite(t_us):
            raise UserError(f"detect time must be finite, got {t_us}")
        if t_us < self._last_t:
            raise UserError(f"detect time {t_us:g} us is earlier than the latest event ({self._last_t:g} us)")
        if self.hybrid and self._t_image is None:
            raise UserError("a hybrid model needs an image before it can detect: call push_image first")
        if self.hybrid and t_us < self._t_image:
            raise UserError(f"detect time {t_us:g} us is earlier than the image ({self._t_image:g} us)")
        with torch.inference_mode():
            raw, shapes = self._head_outputs(t_us)
            with self._part("decode + NMS"):
                result = postprocess(raw, shapes, self.net.answer_strides(shapes), conf_threshold=self.operating.score,
                                     nms_threshold=self.operating.nms_iou, image_size=(self.height, self.width))[0]
        return {"boxes": result["boxes"].cpu().numpy(), "scores": result["scores"].cpu().numpy(),
                "labels": result["labels"].cpu().numpy(), "t_us": t_us}

    def head_outputs(self, t_us: float) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        """The head's raw output ``(1, A, 5 + C)`` and map shapes at ``t_us`` (no checks)."""
        with torch.inference_mode():
            return self._head_outputs(t_us)

    def _head_outputs(self, t_us: float) -> tuple[torch.Tensor, list[tuple[int, int]]]:
        self._ingest()
        if self._segment is None:  # events-only, no event yet
            first = t_us - self.window_us - self.graph_context_us
            self._start_segment(first, first)
        segment = self._segment
        t_start = self._sample_start(t_us)
        if segment.cells is not None and not np.searchsorted(segment.t_abs.view, t_start, side="left"):
            # No event of the segment has left the horizon: the cells kept up to date serve.
            if segment.maps is None or segment.maps[0] != segment.events.n:  # the pooled stages saw new nodes
                with self._part("pooled stages"):
                    maps = self.net.events.maps_from_first_pool(segment.cells.graph(), self._sampler())
                segment.maps = (segment.events.n, maps)
            event_maps = segment.maps[1]
        else:
            with self._part("horizon start + pooled stages"):
                event_maps = self._window_maps(t_start)
        return self._head(event_maps, t_us, t_start, segment.origin_us)

    def _sample_start(self, t_us: float) -> float:
        """The start of the events the model reads at ``t_us`` (the batch sample's, :func:`sample_start_us`)."""
        return sample_start_us(t_us, self.window_us, self._t_image if self.hybrid else None, self.context_us)

    def _graph_start(self, t_us: float) -> float:
        """The earliest event the graph's first stage reads at ``t_us`` (the sample's start, less its graph context)."""
        return self.sample.graph_start_us(t_us, self._t_image if self.hybrid else None)

    def _head(self, event_maps: list[torch.Tensor], t_us: float, t_start: float, origin: float):
        image_maps = self._image[0] if self.hybrid else None
        model = self.net
        if model.cfg.late_query:
            with self._part("head towers (changed cells)"):
                self._segment.towers.update(image_maps, event_maps)
        with self._part("recency + query head (all cells)" if model.cfg.late_query else "recency + fusion + head"):
            # A cell whose latest event left the horizon has none in the sample.
            recency = [recency_since(latest, h, w, t_start - origin, t_us - origin, model.cfg.recency_us)
                       for latest, (h, w) in zip(self._segment.latest, self.map_sizes)]
            age = torch.tensor([t_us - (self._t_image if self.hybrid else origin)], dtype=torch.float64,
                               device=self.device)
            if model.cfg.late_query:
                return self._segment.towers.answer(model.query_maps(recency, age))
        carry_maps = None
        if self._carry is not None:
            with self._part("carry picture + branch"):
                picture = self._carry.picture(t_us)
                if self._split_carry:  # the frame's share computed when it came
                    carry_maps = model.picture_maps_from(self._carry_frame_part, self._pixels(picture))
                else:
                    parts = [self._frame, picture] if model.cfg.carry_frame else [picture]  # the frame beside the picture
                    carry_maps = model.picture_maps(self._pixels(*parts))
        with self._part("recency + fusion + head"):
            event_inputs = model.event_head_inputs(event_maps, recency) if model.cfg.event_answers else None
            return model.answer_outputs(*model.combine(image_maps, event_maps, recency, age, carry_maps,
                                                       image_parts=self._fusion_image), event_inputs)

    # ---------------------------------------------------------------- internals
    @contextmanager
    def _part(self, name: str):
        """Adds the time spent inside to ``timings[name]`` when profiling."""
        if self.timings is None:
            yield
            return
        start = time.perf_counter()
        yield
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - start

    def _sampler(self):
        return self._image[2] if self.hybrid else None

    def _pixels(self, *parts: np.ndarray) -> torch.Tensor:
        """``(H, W, C_i)`` uint8 pictures, channels joined in order, as the ``(1, sum C_i, H, W)`` batch the
        model reads (the dataset's :func:`~dagr_lite.data.dataset.channels_first`), laid out channels last:
        a view of the joined pictures, which the packed convolutions read without a copy."""
        joined = np.ascontiguousarray(parts[0]) if len(parts) == 1 else np.concatenate(parts, axis=2)
        if not joined.flags.writeable:  # a caller's read-only frame: torch reads only writable arrays
            joined = joined.copy()
        return torch.from_numpy(joined).permute(2, 0, 1)[None].to(self.device)

    def _add_to_carry(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        """Adds events (kept by the arrival filters) to the carry picture's state: those since the
        image are counted, those just before it may confirm them."""
        if self._carry is not None:
            self._carry.add(x, y, t, p)

    def _start_segment(self, origin_us: float, first_us: float, keep_from_us: float | None = None) -> None:
        """A new segment from ``origin_us``, fed with the logged events since ``first_us``; the log
        keeps those since ``first_us`` or, when earlier, ``keep_from_us``."""
        t = self._log["t"].view
        keep_from = first_us if keep_from_us is None else min(first_us, keep_from_us)
        self._trim_log(int(np.searchsorted(t, keep_from, side="left")), keep_from)
        self._done = 0
        self._segment = _Segment(self, origin_us)
        self._segment.first_us = first_us
        self._ingest()

    def _trim_log(self, first: int, t_us: float) -> None:
        """Forget the first ``first`` logged events (all before ``t_us``)."""
        if first:
            for rows in self._log.values():
                rows.drop_front(first)
            self._done = max(0, self._done - first)
            self._kept_from = max(self._kept_from, t_us)

    def _ingest(self) -> None:
        """Bring the segment up to the logged events, and forget what no later answer can read."""
        log = self._log
        if self.hybrid and self._segment is None:  # no image yet: keep what a late image may need
            keep_from = self._last_t - MAX_IMAGE_DELAY_US - self._lead_us
            self._trim_log(int(np.searchsorted(log["t"].view, keep_from, side="left")), keep_from)
            return
        if not self.hybrid:
            if not log["t"].n and self._segment is None:
                return
            t_start = self._last_t - self.window_us - self.graph_context_us  # the earliest any later answer reads
            if self._segment is None or self._last_t - self._segment.origin_us > REORIGIN_US:
                self._start_segment(t_start, t_start)  # ingests the window again
                return
            self._trim_log(min(self._done, int(np.searchsorted(log["t"].view, t_start, side="left"))), t_start)
        else:
            t_start = self._graph_start(self._last_t)  # the earliest event any later answer reads
            # A later image (not older than this one) may need the events since its time - _lead_us.
            keep_from = max(self._t_image, self._last_t - MAX_IMAGE_DELAY_US) - self._lead_us
            self._trim_log(min(self._done, int(np.searchsorted(log["t"].view, keep_from, side="left"))), keep_from)
        self._expire(t_start)
        end = log["t"].n
        if self.hybrid:  # events pushed after the image but from before its context are not the sample's
            self._done = max(self._done, int(np.searchsorted(log["t"].view, self._segment.first_us, side="left")))
        if end > self._done:
            self._add(*(log[key].view[self._done:end] for key in ("x", "y", "t", "p")))
            self._done = end

    def _add(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        """New events into the graph, the first stage (new nodes only), the cells and the recency times."""
        segment, branch = self._segment, self.net.events
        events = torch.from_numpy(np.stack([x, y, t - segment.origin_us, p], axis=1)).to(self.device, self.dtype)
        spec = self.net.graph_spec
        pos = spec.positions(events)  # (M, 3)
        exact = spec.positions(events.double())  # float64, exact: the graph's and the geometry's
        with self._part("graph"):
            edges = segment.graph.insert(exact).to(self.device)  # (2, E) global ids
        old, m = segment.events.n, len(events)
        first_id = segment.base + old
        segment.events.extend(events)
        segment.t_abs.extend(t)
        segment.pos.extend(pos)
        segment.exact_pos.extend(exact)
        segment.in_degree.extend(torch.bincount(edges[1] - first_id, minlength=m))
        local = edges - segment.base
        # An edge from a node that left the segment (before the earliest window start of any later
        # answer) only reaches nodes in the prefix that each answer recomputes from the window's own
        # graph: the first stage here leaves it out rather than read a row that is gone.
        local = local[:, local[0] >= 0]
        batch = torch.zeros(m, dtype=torch.int64, device=self.device)
        with self._part("first stage (new nodes)"):
            features = branch.node_features(events, segment.exact_pos.view, local, first=old)
            segment.h[0].extend(branch.level_input(0, features, pos, batch, self._sampler()))
            op = branch.stage_graph(0, segment.h[0].view, local, segment.exact_pos.view,
                                    in_degree=segment.in_degree.view, first=old)
            for b, block in enumerate(branch.first_stage):
                segment.h[b + 1].extend(block(segment.h[b].view, op))
        with self._part("cells + recency times"):
            self._update_cells(segment, events, pos, batch, edges, old)

    def _update_cells(self, segment: _Segment, events: torch.Tensor, pos: torch.Tensor, batch: torch.Tensor,
                      edges: torch.Tensor, old: int) -> None:
        """The new nodes' edges (rows from ``old``); a hybrid's first pooled cells take them in while
        they serve. The latest event time of every recency cell."""
        segment.edges.extend(edges.T)
        if segment.cells is not None:
            segment.cell.extend(segment.cells.cell_of(pos))
            cell = segment.cell.view
            segment.cells.add(segment.h[-1].view[old:], pos, cell[old:], cell[edges - segment.base])
        for latest, stride, (h, w) in zip(segment.latest, self.net.strides, self.map_sizes):
            if compiled_for(events):  # one compiled pass, the same maxima
                latest_times(latest.numpy(), events.contiguous().numpy(), stride, h, w)
                continue
            key = recency_cells(events, batch, stride=stride, height=h, width=w)
            latest.scatter_reduce_(0, key, events[:, 2], reduce="amax")

    def _expire(self, t_start: float) -> None:
        """Forget the segment's rows older than the horizon once they are half of it."""
        segment = self._segment
        first = int(np.searchsorted(segment.t_abs.view, t_start, side="left"))
        if first < max(1024, segment.events.n // 2):
            return
        for rows in (segment.events, segment.t_abs, segment.pos, segment.exact_pos, segment.in_degree, *segment.h):
            rows.drop_front(first)
        segment.base += first
        segment.cells = None  # its cells hold nodes that left: the horizon's own serve from now on
        edges = segment.edges.view
        segment.edges.drop_front(int(torch.searchsorted(edges[:, 1].contiguous(), segment.base)))

    def _window_maps(self, t_start: float) -> list[torch.Tensor]:
        """The dense maps over the events since ``t_start``: the nodes of the first ``reach_us`` of
        the horizon recomputed from its events, the rest cached; with a graph context every node
        is cached (its features never depend on the horizon's start) and only the pooling is redone."""
        segment, branch, spec = self._segment, self.net.events, self.net.graph_spec
        sampler = self._sampler()
        t = segment.t_abs.view
        first = int(np.searchsorted(t, t_start, side="left"))
        if self.graph_context_us:
            edges = None  # dense pooled stages read the nodes' cells alone, not their edges
            if not branch.dense:
                edges = segment.edges.view
                edges = edges[edges[:, 0] >= segment.base + first].T - (segment.base + first)  # both ends in the horizon
            x, pos = segment.h[-1].view[first:], segment.pos.view[first:]
            batch = torch.zeros(len(x), dtype=torch.int64, device=self.device)
            return branch.pooled_maps(x, pos, batch, edges, 1, sampler)
        stable = int(np.searchsorted(t, t_start + self.reach_us * (1 + 1e-9) + 1.0, side="left"))
        stable = max(stable, first)
        # Only the nodes within one radius of the window's start had neighbours before it: their edges
        # are found again among the window's events; the later zone nodes keep the edges they got on
        # arrival (every candidate of theirs lies in the window), though their features change.
        hop = int(np.searchsorted(t, t_start + self.radius_us * (1 + 1e-9) + 1.0, side="left"))
        hop = min(max(hop, first), stable)
        zone = segment.events.view[first:stable]
        zone_batch = torch.zeros(len(zone), dtype=torch.int64, device=self.device)
        edges = segment.edges.view
        dst = edges[:, 1].contiguous()
        from_first, from_hop, from_id = (int(i) for i in torch.searchsorted(dst, torch.tensor([first, hop, stable])
                                                                            + segment.base))
        # Their edges on arrival serve where no candidate from before the window was one of their k nearest.
        head = edges_after(edges[from_first:from_hop], segment.base + first, hop - first, spec.max_neighbors,
                           lambda query: spec.edges(zone[:hop - first], zone_batch[:hop - first], workers=1,
                                                    query=query)).to(self.device)
        zone_edges = torch.cat([head, edges[from_hop:from_id].T - (segment.base + first)], dim=1)
        x_zone, _, _ = branch.event_nodes(zone, zone_batch, sampler, zone_edges)
        x = torch.cat([x_zone, segment.h[-1].view[stable:]])
        pos = segment.pos.view[first:]
        batch = torch.zeros(len(x), dtype=torch.int64, device=self.device)
        edge_index = None  # dense pooled stages read the nodes' cells alone, not their edges
        if not branch.dense:
            edge_index = torch.cat([zone_edges, edges[from_id:].T - (segment.base + first)], dim=1)
        return branch.pooled_maps(x, pos, batch, edge_index, 1, sampler)
