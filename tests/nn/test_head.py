import copy
import math

import pytest
import torch
import torch.nn.functional as F

from dagr_lite.nn.blocks import fold_batch_norms
from dagr_lite.nn.detector import ImageBranch, sample_at
from dagr_lite.nn.head import (YOLOXHead, anchors_of, box_iou, decode_boxes, nms, postprocess, simota_assign,
                               yolox_losses)
from tests.settings import EVAL


def brute_force_nms(boxes, scores, threshold, labels):
    order = sorted(range(len(boxes)), key=lambda i: (-float(scores[i]), i))
    kept = []
    for i in order:
        if all(labels[i] != labels[j] or box_iou(boxes[i:i + 1], boxes[j:j + 1])[0, 0] <= threshold for j in kept):
            kept.append(i)
    return kept


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nms_equals_a_brute_force_reference(dtype):
    """nms (on a CPU: numpy's operations) keeps what a brute-force greedy pass over box_iou keeps,
    class-aware or not, scores tied in index order, boxes on a grid so that IoUs meet the threshold."""
    g = torch.Generator().manual_seed(0)
    for trial in range(30):
        n = int(torch.randint(0, 60, (1,), generator=g))
        xy = torch.rand(n, 2, generator=g) * 50
        boxes = torch.cat([xy, xy + 5 + torch.rand(n, 2, generator=g) * 20], 1).to(dtype)
        if trial % 3 == 0:
            boxes = boxes.round()  # equal IoUs, some exactly at a threshold
        scores = torch.rand(n, generator=g).to(dtype)
        if trial % 2:
            scores = (scores * 4).round() / 4  # ties
        labels = torch.randint(0, 2, (n,), generator=g)
        for threshold in (0.3, 0.5, 0.65):
            assert nms(boxes, scores, threshold, labels).tolist() == brute_force_nms(boxes, scores, threshold, labels)
            assert nms(boxes, scores, threshold).tolist() == brute_force_nms(boxes, scores, threshold, torch.zeros(n))


def test_anchors_and_decoding_use_the_stride_in_both_axes():
    centres, strides = anchors_of([(2, 3), (1, 2)], [8, 16], "cpu")
    assert centres.tolist()[:4] == [[4, 4], [12, 4], [20, 4], [4, 12]]
    assert centres.tolist()[6:] == [[8, 8], [24, 8]] and strides.tolist() == [8] * 6 + [16] * 2
    raw = torch.zeros(1, 8, 4)
    raw[0, 5] = torch.tensor([0.5, -0.25, 0.0, torch.log(torch.tensor(2.0))])  # cell (row 1, col 2) at stride 8
    boxes = decode_boxes(raw, centres, strides)[0, 5]
    # centre (20 + 4, 12 - 2), size (8, 16)
    assert boxes.tolist() == [20.0, 2.0, 28.0, 18.0]


def test_simota_gives_a_box_its_centre_cells_within_dynamic_k_bounds():
    shapes, strides = [(8, 8)], [8]
    centres, stride_of = anchors_of(shapes, strides, "cpu")
    gt = torch.tensor([[16.0, 16.0, 40.0, 40.0]])  # centre (28, 28): cells with centres 20..36
    # Predictions: every anchor predicts the GT box exactly, so all candidates have IoU 1.
    pred = gt.expand(len(centres), 4).clone()
    a = simota_assign(pred, torch.zeros(64), torch.zeros(64, 1), gt, torch.zeros(1, dtype=torch.long), centres, stride_of)
    fg_centres = centres[a.fg].tolist()
    assert int(a.fg.sum()) == 10  # dynamic k = sum of the top-10 IoUs, all 1 here
    inside = [[x, y] for y in (20.0, 28.0, 36.0) for x in (20.0, 28.0, 36.0)]  # centres in the box and near its centre
    assert all(c in fg_centres for c in inside)  # the cheapest anchors: all nine are taken
    assert all(abs(x - 28) < 2.5 * 8 and abs(y - 28) < 2.5 * 8 for x, y in fg_centres)  # all within the centre prior
    assert a.gt_index.tolist() == [0] * int(a.fg.sum()) and torch.allclose(a.iou, torch.ones_like(a.iou))
    # Poor predictions everywhere: k falls to its floor of one anchor.
    far = torch.tensor([[200.0, 200.0, 210.0, 210.0]]).expand(64, 4)
    b = simota_assign(far, torch.zeros(64), torch.zeros(64, 1), gt, torch.zeros(1, dtype=torch.long), centres, stride_of)
    assert int(b.fg.sum()) == 1
    none = simota_assign(pred, torch.zeros(64), torch.zeros(64, 1), torch.zeros((0, 4)), torch.zeros(0, dtype=torch.long),
                         centres, stride_of)
    assert not none.fg.any()


def test_an_anchor_claimed_by_two_boxes_goes_to_the_cheaper_one():
    # Two overlapping boxes of the same class; on an 8x8 map at stride 8 both have the cells with centres
    # {20, 28, 36}^2 inside the box and near the centre. Every anchor predicts a far box (IoU 0) except:
    #   Y (20, 20) predicts box 0 exactly:    IoU 1 with box 0, 784 / 1264 = 0.620 with box 1;
    #   X (36, 36) predicts [11, 11, 43, 43]: IoU 841 / 1207 = 0.697 with box 0, 961 / 1087 = 0.884 with box 1;
    #   W (28, 20) predicts [8, 8, 28, 28]:   IoU 400 / 1024 = 0.391 with box 0, 256 / 1168 = 0.219 with box 1.
    # Dynamic k: box 0 int(1 + 0.697 + 0.391) = 2 -> Y and X; box 1 int(0.884 + 0.620 + 0.219) = 1 -> X.
    # X is claimed by both and costs less for box 1 (-log 0.884 < -log 0.697), so X goes to box 1 alone.
    centres, stride_of = anchors_of([(8, 8)], [8], "cpu")
    gt = torch.tensor([[8.0, 8.0, 40.0, 40.0], [12.0, 12.0, 44.0, 44.0]])
    y, w, x = 2 * 8 + 2, 2 * 8 + 3, 4 * 8 + 4
    pred = torch.tensor([[200.0, 200.0, 210.0, 210.0]]).repeat(64, 1)
    pred[y], pred[x], pred[w] = gt[0], torch.tensor([11.0, 11.0, 43.0, 43.0]), torch.tensor([8.0, 8.0, 28.0, 28.0])
    iou = box_iou(gt, pred[[y, x, w]])
    assert torch.allclose(iou, torch.tensor([[1.0, 841 / 1207, 400 / 1024], [784 / 1264, 961 / 1087, 256 / 1168]]))
    labels = torch.zeros(2, dtype=torch.long)
    a = simota_assign(pred, torch.zeros(64), torch.zeros(64, 1), gt, labels, centres, stride_of)
    assert torch.nonzero(a.fg).flatten().tolist() == [y, x]
    assert a.gt_index.tolist() == [0, 1]
    assert torch.allclose(a.iou, torch.tensor([1.0, 961 / 1087]))
    # The same boxes listed the other way round: the same anchors, the same boxes.
    b = simota_assign(pred, torch.zeros(64), torch.zeros(64, 1), gt.flip(0), labels, centres, stride_of)
    assert torch.nonzero(b.fg).flatten().tolist() == [y, x]
    assert b.gt_index.tolist() == [1, 0]
    assert torch.allclose(b.iou, torch.tensor([1.0, 961 / 1087]))


def test_bilinear_node_sampling_equals_grid_sample():
    g = torch.Generator().manual_seed(0)
    feature = torch.randn(2, 3, 5, 7, generator=g)
    xy = torch.rand(40, 2, generator=g) * torch.tensor([7 * 8 - 1.0, 5 * 8 - 1.0])
    batch = torch.randint(0, 2, (40,), generator=g)
    ours = sample_at(feature, xy, batch, 8)
    for i in range(40):
        u = (xy[i, 0] + 0.5) / (7 * 8) * 2 - 1
        v = (xy[i, 1] + 0.5) / (5 * 8) * 2 - 1
        grid = torch.stack([u, v]).view(1, 1, 1, 2)
        ref = F.grid_sample(feature[batch[i]][None], grid, align_corners=False, padding_mode="border")
        assert torch.allclose(ours[i], ref.flatten(), atol=1e-5)


def test_branch_and_head_shapes():
    maps = ImageBranch(width=8, strides=(8, 16, 32))(torch.zeros(2, 3, 180, 320, dtype=torch.uint8))
    assert [tuple(m.shape) for m in maps] == [(2, 16, 45, 80), (2, 32, 23, 40), (2, 64, 12, 20), (2, 128, 6, 10)]
    head = YOLOXHead([32, 64, 128], [8, 16, 32], hidden=16, num_classes=1)
    raw, shapes = head(maps[1:])
    assert raw.shape == (2, 23 * 40 + 12 * 20 + 6 * 10, 6) and shapes == [(23, 40), (12, 20), (6, 10)]
    dets = postprocess(raw, shapes, [8, 16, 32], image_size=(180, 320), **EVAL)
    assert len(dets) == 2 and dets[0]["boxes"].shape[1] == 4 and len(dets[0]["boxes"]) <= 100
    assert torch.all(dets[0]["boxes"][:, 2] <= 320) and torch.all(dets[0]["boxes"][:, 3] <= 180)


def test_image_branch_gives_out_the_head_strides_only():
    """Strides from 16 keep the stride-8 stage (it leads to 16) but give out only the stride-4
    map and the head's; the layers, and so the weights, are those of [8, 16, 32]."""
    torch.manual_seed(0)
    full = ImageBranch(width=8, strides=(8, 16, 32))
    coarse = ImageBranch(width=8, strides=(16, 32))
    assert coarse.strides == (4, 16, 32) and coarse.channels == (16, 64, 128)
    coarse.load_state_dict(full.state_dict())  # same layers
    images = torch.randint(0, 255, (2, 3, 180, 320), dtype=torch.uint8)
    full.eval(), coarse.eval()
    every, given = full(images), coarse(images)
    assert len(given) == 3 and all(torch.equal(a, b) for a, b in zip(given, [every[0], every[2], every[3]]))
    for bad in ((4, 8), (8, 32), (12, 24), (16,) * 2, ()):
        with pytest.raises(ValueError, match="strides that double"):
            ImageBranch(width=8, strides=bad)


@pytest.mark.parametrize("height, width", [(180, 320), (181, 322), (35, 61)])
def test_both_image_stems_give_the_same_map_sizes(height, width):
    images = torch.zeros(2, 3, height, width, dtype=torch.uint8)
    shapes = {stem: [tuple(m.shape) for m in ImageBranch(width=8, strides=(8, 16, 32), stem=stem)(images)]
              for stem in ("patch", "conv")}
    assert shapes["patch"] == shapes["conv"]
    assert shapes["patch"][0] == (2, 16, -(-height // 4), -(-width // 4))  # ceil(H / 4), ceil(W / 4)
    with pytest.raises(ValueError, match="image_stem must be one of \\['patch', 'conv'\\], got 'vit'"):
        ImageBranch(width=8, strides=(8, 16, 32), stem="vit")


def test_the_patch_stem_reads_each_cells_own_four_by_four_pixels():
    """A pixel changes exactly the stride-4 cell that holds it (before the residual block mixes
    neighbours): cell (i, j) covers pixels [4i, 4i + 4) x [4j, 4j + 4), as the node sampler
    assumes; a frame cut mid-patch is padded on the right and bottom only."""
    torch.manual_seed(0)
    branch = ImageBranch(width=8, strides=(8, 16, 32), stem="patch").eval()
    patchify = branch.stem[0][0]  # the 4x4 stride-4 convolution
    images = torch.randint(0, 255, (1, 3, 22, 30), dtype=torch.uint8)
    padded = F.pad(images.float() / 255.0 - 0.5, (0, 2, 0, 2))  # 22 x 30 -> 24 x 32
    with torch.no_grad():
        reference = patchify(padded)
        assert reference.shape[-2:] == (6, 8)
        for y, x in ((0, 0), (5, 13), (21, 29), (20, 3)):
            changed = padded.clone()
            changed[0, :, y, x] += 0.7
            moved = (patchify(changed) - reference).abs().sum(dim=1)[0] > 1e-6  # (6, 8)
            expected = torch.zeros(6, 8, dtype=torch.bool)
            expected[y // 4, x // 4] = True
            assert torch.equal(moved, expected)
        # The branch pads the same way: its stride-4 map is the stem on the padded frame.
        torch.testing.assert_close(branch(images)[0], branch.stem(padded))


def sigmoid(x: float) -> float:
    return 1 / (1 + math.exp(-x))


def bce(logit: float, target: float) -> float:
    p = sigmoid(logit)
    return -(target * math.log(p) + (1 - target) * math.log(1 - p))


def postprocess_raw() -> torch.Tensor:
    """Two images on one 2 x 2 map at stride 8 (anchors (4, 4), (12, 4), (4, 12), (12, 12)), two classes."""
    ln2 = math.log(2)
    raw = torch.full((2, 4, 7), -8.0)  # image 1: every score sigmoid(-8)^2 < 1e-6
    raw[0, 0] = torch.tensor([0.0, 0.0, ln2, ln2, 2.0, 1.0, -1.0])  # centre (4, 4), 16 x 16, class 0
    raw[0, 1] = torch.tensor([0.25, 0.0, ln2, 0.0, 1.0, 0.5, -2.0])  # centre (14, 4), 16 x 8, class 0
    raw[0, 2] = torch.tensor([0.0, -0.5, ln2, ln2, 3.0, -3.0, 0.0])  # centre (4, 8), 16 x 16, class 1
    raw[0, 3] = torch.tensor([0.0, 0.0, 0.0, 0.0, -5.0, -5.0, -6.0])  # centre (12, 12), 8 x 8, below threshold
    return raw


def test_postprocess_decodes_scores_clamps_and_suppresses_by_hand():
    raw, shapes, strides = postprocess_raw(), [(2, 2)], [8]
    s0, s1, s2 = sigmoid(2) * sigmoid(1), sigmoid(1) * sigmoid(0.5), sigmoid(3) * sigmoid(0)  # 0.644, 0.455, 0.476
    unclamped = {0: [-4.0, -4.0, 12.0, 12.0], 1: [6.0, 0.0, 22.0, 8.0], 2: [-4.0, 0.0, 12.0, 16.0]}
    clamped = {0: [0.0, 0.0, 12.0, 12.0], 1: [6.0, 0.0, 20.0, 8.0], 2: [0.0, 0.0, 12.0, 16.0]}  # image 16 x 20
    # Same class, clamped: boxes 0 and 1 share [6, 12] x [0, 8] = 48 px of 144 + 112 - 48 -> IoU 0.231.
    # Unclamped they share the same 48 px of 256 + 128 - 48 -> IoU 0.143. Box 2 is of the other class.
    assert abs(48 / (144 + 112 - 48) - 0.2308) < 1e-4 and abs(48 / (256 + 128 - 48) - 0.1429) < 1e-4

    def check(det, order, boxes):
        assert det["labels"].tolist() == [{0: 0, 1: 0, 2: 1}[i] for i in order]
        assert torch.allclose(det["scores"], torch.tensor([{0: s0, 1: s1, 2: s2}[i] for i in order]))
        assert torch.allclose(det["boxes"], torch.tensor([boxes[i] for i in order]).reshape(-1, 4), atol=1e-5)

    dets = postprocess(raw, shapes, strides, conf_threshold=0.01, nms_threshold=0.2, image_size=(16, 20))
    check(dets[0], [0, 2], clamped)  # 1 falls to 0 (IoU 0.231 > 0.2); 3 is below the threshold
    assert dets[1]["boxes"].shape == (0, 4) and len(dets[1]["scores"]) == 0 and len(dets[1]["labels"]) == 0
    dets = postprocess(raw, shapes, strides, conf_threshold=0.01, nms_threshold=0.2)
    check(dets[0], [0, 2, 1], unclamped)  # without clamping the overlap is only 0.143
    dets = postprocess(raw, shapes, strides, conf_threshold=0.01, nms_threshold=0.5, image_size=(16, 20))
    check(dets[0], [0, 2, 1], clamped)
    for limit, order in ((2, [0, 2]), (1, [0])):
        dets = postprocess(raw, shapes, strides, conf_threshold=0.01, nms_threshold=0.5, max_detections=limit,
                           image_size=(16, 20))
        check(dets[0], order, clamped)
    dets = postprocess(raw, shapes, strides, conf_threshold=0.46, nms_threshold=0.5, image_size=(16, 20))
    check(dets[0], [0, 2], clamped)  # 0.455 < 0.46 <= 0.476
    dets = postprocess(raw, shapes, strides, conf_threshold=0.0, nms_threshold=0.5, image_size=(16, 20))
    s3 = sigmoid(-5) * sigmoid(-5)
    assert torch.allclose(dets[0]["scores"], torch.tensor([s0, s2, s1, s3]))
    assert dets[0]["boxes"][-1].tolist() == [8.0, 8.0, 16.0, 16.0] and dets[0]["labels"][-1] == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("image_size", [None, (40, 56)])
def test_postprocess_on_a_cpu_in_numpy_equals_the_tensor_operations(dtype, image_size):
    """The numpy path a CPU takes and the tensor path of other devices: the same boxes kept, in the
    same order, with scores and boxes equal to their exponentials' rounding; two classes, boxes
    past the image, more candidates than ``pre_nms``, an image without any."""
    from dagr_lite.nn.head import _postprocess_tensors

    g = torch.Generator().manual_seed(3)
    shapes, strides = [(5, 7), (3, 4)], [8, 16]
    raw = torch.randn(3, 47, 7, generator=g, dtype=dtype) * 2
    raw[2, :, 4] = -20.0  # no candidate
    for pre_nms in (1000, 9):
        want = _postprocess_tensors(raw, *anchors_of(shapes, strides, "cpu"), 0.05, 0.5, 100, pre_nms, image_size)
        got = postprocess(raw, shapes, strides, conf_threshold=0.05, nms_threshold=0.5, pre_nms=pre_nms,
                          image_size=image_size)
        tolerance = 1e-5 if dtype == torch.float32 else 1e-12
        for a, b in zip(got, want):
            assert a["labels"].tolist() == b["labels"].tolist() and a["labels"].dtype == torch.int64
            assert a["boxes"].shape == b["boxes"].shape and a["boxes"].dtype == b["boxes"].dtype == dtype
            torch.testing.assert_close(a["scores"], b["scores"], rtol=tolerance, atol=tolerance)
            torch.testing.assert_close(a["boxes"], b["boxes"], rtol=tolerance, atol=tolerance)
        assert len(got[0]["scores"]) > 1 and len(got[2]["scores"]) == 0
        assert len(got[1]["scores"]) <= pre_nms


def loss_case():
    """One GT [2, 2, 7, 7] on a 2 x 2 map at stride 8: only anchor 0 (4, 4) lies inside it."""
    raw = torch.zeros(1, 4, 6)
    raw[0, 0, :4] = torch.tensor([0.1, -0.2, math.log(0.5), 0.0])  # centre (4.8, 2.4), 4 x 8: [2.8, -1.6, 6.8, 6.4]
    raw[0, :, 4] = torch.tensor([0.3, -1.0, 2.0, -0.5])  # objectness
    raw[0, :, 5] = torch.tensor([0.7, 0.2, -0.4, 1.1])  # class
    # The other anchors predict 8 x 8 boxes at their centres, [8, 0, 16, 8] ...: no overlap with the GT, so
    # dynamic k = int(IoU of anchor 0) = 0 -> 1, and only anchor 0 is in the box and near its centre.
    return raw, [(2, 2)], [8], torch.tensor([[2.0, 2.0, 7.0, 7.0]]), torch.zeros(1, dtype=torch.long)


def test_yolox_losses_of_one_forced_match_by_hand():
    raw, shapes, strides, gt, labels = loss_case()
    iou = (4.0 * 4.4) / (25 + 32 - 4.0 * 4.4)  # overlap [2.8, 6.8] x [2, 6.4]; areas 5 x 5 and 4 x 8
    obj = bce(0.3, 1) + bce(-1.0, 0) + bce(2.0, 0) + bce(-0.5, 0)
    cls = bce(0.7, iou)  # the class target of a foreground anchor is its IoU
    for weight in (5.0, 2.0):
        out = yolox_losses(raw, shapes, strides, [gt], [labels], iou_weight=weight)
        assert out["num_fg"].item() == 1
        assert math.isclose(out["iou_loss"].item(), 1 - iou ** 2, rel_tol=1e-5)
        assert math.isclose(out["obj_loss"].item(), obj, rel_tol=1e-5)
        assert math.isclose(out["cls_loss"].item(), cls, rel_tol=1e-5)
        assert math.isclose(out["loss"].item(), weight * (1 - iou ** 2) + obj + cls, rel_tol=1e-5)
    # A second image without boxes adds its objectness terms; the normaliser is still the one match.
    raw2 = torch.cat([raw, raw], 0)
    out = yolox_losses(raw2, shapes, strides, [gt, torch.zeros(0, 4)], [labels, torch.zeros(0, dtype=torch.long)])
    obj2 = obj + bce(0.3, 0) + bce(-1.0, 0) + bce(2.0, 0) + bce(-0.5, 0)
    assert out["num_fg"].item() == 1 and math.isclose(out["obj_loss"].item(), obj2, rel_tol=1e-5)
    assert math.isclose(out["loss"].item(), 5 * (1 - iou ** 2) + obj2 + cls, rel_tol=1e-5)


def test_yolox_losses_without_boxes_are_objectness_only():
    raw, shapes, strides, _, _ = loss_case()
    raw.requires_grad_(True)
    out = yolox_losses(raw, shapes, strides, [torch.zeros(0, 4)], [torch.zeros(0, dtype=torch.long)])
    obj = bce(0.3, 0) + bce(-1.0, 0) + bce(2.0, 0) + bce(-0.5, 0)  # every target 0, divided by max(0, 1)
    assert out["num_fg"].item() == 0 and out["iou_loss"].item() == 0 and out["cls_loss"].item() == 0
    assert math.isclose(out["obj_loss"].item(), obj, rel_tol=1e-5)
    assert math.isclose(out["loss"].item(), obj, rel_tol=1e-5)
    out["loss"].backward()
    expected = torch.tensor([sigmoid(x) for x in (0.3, -1.0, 2.0, -0.5)])  # d BCE(x, 0) / dx = sigmoid(x)
    assert torch.allclose(raw.grad[0, :, 4], expected) and not raw.grad[0, :, :4].any() and not raw.grad[0, :, 5].any()


def test_a_late_head_refuses_missing_or_unexpected_query_maps_and_image():
    late = YOLOXHead([8], [8], hidden=4, num_classes=1, late_channels=2, image_channels=[6])
    maps, query, image = [torch.zeros(1, 8, 3, 3)], [torch.zeros(1, 2, 3, 3)], [torch.zeros(1, 6, 3, 3)]
    raw, shapes = late(maps, query, image)
    assert raw.shape == (1, 9, 6) and shapes == [(3, 3)]
    with pytest.raises(ValueError, match="reads 2 query channels after its towers and an image input, got no query"):
        late(maps, None, image)
    with pytest.raises(ValueError, match="got some query maps and no image"):
        late(maps, query)
    with pytest.raises(ValueError, match="reads 0 query channels .* got some query maps"):
        YOLOXHead([8], [8], hidden=4, num_classes=1)(maps, query)
    with pytest.raises(ValueError, match="image_channels needs late_channels > 0"):
        YOLOXHead([8], [8], hidden=4, num_classes=1, image_channels=[6])


@pytest.mark.parametrize("stem", ["patch", "conv"])
def test_an_image_of_six_channels_is_the_frame_and_its_picture_each_read(stem):
    """With ``in_channels=6`` the stem reads all six: the first three as a 3-channel branch with
    the same weights does, the last three through weights of their own."""
    torch.manual_seed(0)
    rgb, six = ImageBranch(8, (8, 16), stem, 3).eval(), ImageBranch(8, (8, 16), stem, 6).eval()
    state = six.state_dict()
    first = "stem.0.0.weight"
    assert state[first].shape[1] == 6
    with torch.no_grad():
        six.stem[0][0].weight[:, 3:] = 0  # the picture's weights off: the frame's branch alone
    rgb.load_state_dict({**six.state_dict(), first: six.state_dict()[first][:, :3]})
    images = torch.randint(0, 255, (2, 6, 35, 61), dtype=torch.uint8)
    mid_grey = images.clone()
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(six(images), rgb(images[:, :3])))
    with torch.no_grad():
        six.stem[0][0].weight[:, 3:] = 0.1
    mid_grey[:, 3:] = 0
    assert not torch.allclose(six(images)[0], six(mid_grey)[0])  # the picture now counts


@pytest.mark.parametrize("height, width", [(180, 320), (35, 61)])
def test_raw_pixels_fold_gives_the_scaled_branch(height, width):
    """read_raw_pixels folds x / 255 - 0.5 into the patch stem: the same maps (float64, 1e-9), a channels-last
    input read as it is, and the grey edge of a frame that is no whole number of patches kept grey."""
    torch.manual_seed(0)
    scaled = ImageBranch(width=4, strides=(8, 16, 32), in_channels=5).double().eval()
    with torch.no_grad():
        for m in scaled.modules():
            if isinstance(m, torch.nn.BatchNorm2d):  # statistics of a trained branch, not the identity
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    raw = copy.deepcopy(scaled).read_raw_pixels()
    assert raw.raw_pixels and raw.read_raw_pixels() is raw  # a second call folds nothing more
    images = torch.randint(0, 256, (1, height, width, 5), dtype=torch.uint8).permute(0, 3, 1, 2)  # channels last
    with torch.no_grad():
        for want, got in zip(scaled(images.contiguous()), raw(images)):
            torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="patch stem"):
        ImageBranch(width=4, strides=(8, 16, 32), stem="conv").read_raw_pixels()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_merged_branches_give_the_head_of_branches_apart(dtype):
    """merge_branches: one tower of two groups and one prediction layer per stride, the same raw output."""
    torch.manual_seed(0)
    head = YOLOXHead([8, 12, 16], [8, 16, 32], hidden=16, num_classes=2).to(dtype).eval()
    with torch.no_grad():
        for m in head.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
    maps = [torch.randn(2, c, h, w, dtype=dtype) for c, (h, w) in zip([8, 12, 16], [(9, 13), (5, 7), (3, 4)])]
    with torch.no_grad():
        want, shapes = head(maps)
        with pytest.raises(ValueError, match="fold the batch norms"):
            copy.deepcopy(head).merge_branches()
        merged = fold_batch_norms(copy.deepcopy(head)).merge_branches()
        assert merged.merged is not None and merged.merge_branches() is merged
        got, got_shapes = merged(maps)
    tolerance = 1e-9 if dtype == torch.float64 else 1e-5
    assert got_shapes == shapes
    torch.testing.assert_close(got, want, rtol=tolerance, atol=tolerance)
    late = YOLOXHead([8], [8], hidden=16, num_classes=1, late_channels=3)
    with pytest.raises(ValueError, match="keeps its branches"):
        late.merge_branches()


def test_split_stem_gives_the_whole_stem():
    """split_stem: the fixed channels' share once, the rest per call; the same maps (float64, 1e-9)."""
    torch.manual_seed(0)
    branch = ImageBranch(width=4, strides=(8, 16, 32), in_channels=7).double().eval()
    with pytest.raises(ValueError, match="split_stem needs"):
        copy.deepcopy(branch).split_stem(3)  # the batch norm not folded, the pixels scaled
    split = fold_batch_norms(copy.deepcopy(branch)).read_raw_pixels().split_stem(3)
    images = torch.randint(0, 256, (1, 7, 35, 61), dtype=torch.uint8)
    with torch.no_grad():
        got = split.forward_from(split.fixed_part(images[:, :3]), images[:, 3:])
        for want, one in zip(branch(images), got):
            torch.testing.assert_close(one, want, rtol=1e-9, atol=1e-9)
    with pytest.raises(ValueError, match="0 < fixed < 7"):
        fold_batch_norms(copy.deepcopy(branch)).read_raw_pixels().split_stem(7)
