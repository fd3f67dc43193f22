"""The one box IoU / NMS copy against torchvision.ops (the reference implementation), on random boxes with many
overlaps, on exact score ties and on degenerate boxes -- the cases where a hand-written NMS goes wrong."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
tv_ops = pytest.importorskip("torchvision.ops", reason="torchvision (dev extra) is the reference")

from vslam.nn.ops import batched_nms, box_iou, box_iou_np, box_iou_paired, nms  # noqa: E402


def _boxes(n: int, seed: int, size: float = 200.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * size
    wh = torch.rand(n, 2, generator=g) * size / 3 + 1
    return torch.cat([xy, xy + wh], 1)


@pytest.mark.parametrize("seed", range(5))
def test_box_iou_equals_torchvision(seed):
    a, b = _boxes(40, seed), _boxes(30, seed + 100)
    ref = tv_ops.box_iou(a, b)
    assert torch.allclose(box_iou(a, b), ref, atol=1e-6)
    assert np.allclose(box_iou_np(a.numpy(), b.numpy()), ref.numpy(), atol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_box_iou_paired_is_the_diagonal(seed):
    a, b = _boxes(40, seed), _boxes(40, seed + 100)
    b[:5] = a[:5]  # some identical pairs (IoU 1), the rest mostly apart
    paired = box_iou_paired(a, b)
    assert torch.equal(paired, torch.diag(box_iou(a, b)))
    assert torch.allclose(paired[:5], torch.ones(5), atol=1e-6) and (paired[5:] < 1).all()


def test_box_iou_np_of_empty_boxes_is_zero_not_nan():
    z = np.zeros((1, 4))
    assert box_iou_np(z, z)[0, 0] == 0.0
    assert box_iou_np(np.zeros((0, 4)), z).shape == (0, 1)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("thr", [0.3, 0.5, 0.7])
def test_nms_equals_torchvision(seed, thr):
    boxes = _boxes(300, seed)  # dense: most boxes overlap several others
    scores = torch.rand(300, generator=torch.Generator().manual_seed(seed + 7))
    assert torch.equal(nms(boxes, scores, thr), tv_ops.nms(boxes, scores, thr))


def test_nms_with_tied_scores_is_a_valid_greedy_result():
    """With exact ties the order among equal scores is free (torchvision's sort is not stable either): what must
    hold is the greedy invariant -- kept boxes never overlap above the threshold, every dropped box overlaps a
    kept one of at least its score -- and as many boxes kept as torchvision keeps, give or take the tie order."""
    boxes = _boxes(200, 3)
    scores = (torch.rand(200, generator=torch.Generator().manual_seed(1)) * 4).floor() / 4  # 4 distinct values
    kept = nms(boxes, scores, 0.5)
    iou = tv_ops.box_iou(boxes, boxes)
    k = kept.tolist()
    assert all(iou[i, j] <= 0.5 for i in k for j in k if i != j)
    dropped = sorted(set(range(200)) - set(k))
    assert all(((iou[d, kept] > 0.5) & (scores[kept] >= scores[d])).any() for d in dropped)
    assert abs(len(k) - len(tv_ops.nms(boxes, scores, 0.5))) <= 10
    assert torch.all(scores[kept][:-1] >= scores[kept][1:])


@pytest.mark.parametrize("seed", range(4))
def test_batched_nms_equals_torchvision(seed):
    boxes = _boxes(200, seed)
    g = torch.Generator().manual_seed(seed + 50)
    scores, classes = torch.rand(200, generator=g), torch.randint(0, 4, (200,), generator=g)
    assert torch.equal(batched_nms(boxes, scores, classes, 0.5), tv_ops.batched_nms(boxes, scores, classes, 0.5))


def test_empty_input_gives_empty_long_indices():
    out = nms(torch.zeros(0, 4), torch.zeros(0), 0.5)
    assert out.shape == (0,) and out.dtype == torch.long
    assert batched_nms(torch.zeros(0, 4), torch.zeros(0), torch.zeros(0, dtype=torch.long), 0.5).dtype == torch.long


def test_importing_ops_does_not_import_torch():
    """The SLAM filter uses the numpy IoU: a run without a network must not pay torch's import."""
    code = "import sys, vslam.nn.ops, vslam.nn.registry, vslam.dynamic.masking; print('torch' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-1500:]
    assert r.stdout.strip() == "False"
