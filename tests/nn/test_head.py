import torch
import torch.nn.functional as F

from dagr_lite.nn.detector import ImageBranch, sample_at
from dagr_lite.nn.head import YOLOXHead, anchors_of, box_iou, decode_boxes, nms, postprocess, simota_assign


def brute_force_nms(boxes, scores, threshold, labels):
    order = sorted(range(len(boxes)), key=lambda i: (-float(scores[i]), i))
    kept = []
    for i in order:
        if all(labels[i] != labels[j] or box_iou(boxes[i:i + 1], boxes[j:j + 1])[0, 0] <= threshold for j in kept):
            kept.append(i)
    return kept


def test_nms_equals_a_brute_force_reference():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        n = int(torch.randint(0, 60, (1,), generator=g))
        xy = torch.rand(n, 2, generator=g) * 50
        boxes = torch.cat([xy, xy + 5 + torch.rand(n, 2, generator=g) * 20], 1)
        scores = torch.rand(n, generator=g)
        labels = torch.randint(0, 2, (n,), generator=g)
        for threshold in (0.3, 0.65):
            assert nms(boxes, scores, threshold, labels).tolist() == brute_force_nms(boxes, scores, threshold, labels)


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


def test_two_boxes_never_share_an_anchor():
    centres, stride_of = anchors_of([(8, 8)], [8], "cpu")
    gt = torch.tensor([[8.0, 8.0, 40.0, 40.0], [16.0, 16.0, 48.0, 48.0]])
    pred = torch.tensor([[12.0, 12.0, 44.0, 44.0]]).expand(64, 4)
    a = simota_assign(pred, torch.zeros(64), torch.zeros(64, 1), gt, torch.zeros(2, dtype=torch.long), centres, stride_of)
    assert len(a.gt_index) == int(a.fg.sum()) and set(a.gt_index.tolist()) <= {0, 1}


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
    maps = ImageBranch(width=8)(torch.zeros(2, 3, 180, 320, dtype=torch.uint8))
    assert [tuple(m.shape) for m in maps] == [(2, 16, 45, 80), (2, 32, 23, 40), (2, 64, 12, 20), (2, 128, 6, 10)]
    head = YOLOXHead([32, 64, 128], [8, 16, 32], hidden=16)
    raw, shapes = head(maps[1:])
    assert raw.shape == (2, 23 * 40 + 12 * 20 + 6 * 10, 6) and shapes == [(23, 40), (12, 20), (6, 10)]
    dets = postprocess(raw, shapes, [8, 16, 32], image_size=(180, 320))
    assert len(dets) == 2 and dets[0]["boxes"].shape[1] == 4 and len(dets[0]["boxes"]) <= 100
    assert torch.all(dets[0]["boxes"][:, 2] <= 320) and torch.all(dets[0]["boxes"][:, 3] <= 180)
