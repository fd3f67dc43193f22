"""The YOLOX loss (vslam.nn.detectors.yolox_loss): SimOTA puts the positives on anchors inside the object, and a
few steps of it teach a small random network a box it could not find before (the fine-tuning path works)."""

from __future__ import annotations

import torch

from vslam.nn.detectors.yolox import STRIDES, YOLOX, grid
from vslam.nn.detectors.yolox_loss import freeze_bn, simota, yolox_loss

SIZE = (64, 96)  # h, w
GT = (torch.tensor([[20.0, 12.0, 52.0, 56.0]]), torch.tensor([1]))


def tiny(seed: int = 0) -> YOLOX:
    torch.manual_seed(seed)
    return YOLOX({"depth": 0.33, "width": 0.125, "classes": ["person", "car"], "input_size": 64})


def test_simota_assigns_anchors_inside_the_box():
    xy, stride = grid([(SIZE[0] // s, SIZE[1] // s) for s in STRIDES], torch.device("cpu"))
    stride = stride[:, 0]
    centres = xy * stride[:, None]
    c = centres + stride[:, None] / 2
    # predictions: every anchor predicts a box of the object's size around its own centre
    boxes = torch.cat([c - torch.tensor([16.0, 22.0]), c + torch.tensor([16.0, 22.0])], 1)
    fg, gt_of, ious = simota(boxes, torch.zeros(len(c), 2), torch.zeros(len(c)), centres, stride, *GT)
    assert 1 <= int(fg.sum()) <= 10
    inside = (c[fg] > GT[0][0, :2]).all(1) & (c[fg] < GT[0][0, 2:]).all(1)
    assert inside.all() and (gt_of[fg] == 0).all() and (ious[fg] > 0.3).all()
    # the object's centre cell (x 36, y 34 at stride 8) is among the positives: its box fits best
    k = int(((c[:, 0] - 36).abs() + (c[:, 1] - 34).abs() + (stride - 8).abs() * 100).argmin())
    assert fg[k]
    empty = simota(boxes, torch.zeros(len(c), 2), torch.zeros(len(c)), centres, stride, torch.zeros((0, 4)),
                   torch.zeros(0, dtype=torch.long))[0]
    assert not empty.any()


def test_a_few_steps_learn_a_box():
    """A fixed image of a bright rectangle on grey; 20 Adam steps from random weights: the loss falls by half and
    the best-scoring box is the rectangle's (IoU 0.67-0.87 over seeds 0-2 at 1 and 2 threads; an untrained network's is
    elsewhere, IoU 0). BatchNorm stays in training mode: random weights have no statistics to freeze."""
    torch.set_num_threads(2)
    img = torch.full((1, 3, *SIZE), 114.0)
    img[..., 12:56, 20:52] = 230.0
    model = tiny().train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(20):
        loss = yolox_loss(model({"image": img}), [GT], SIZE)
        opt.zero_grad()
        loss["loss"].backward()
        opt.step()
        losses.append(float(loss["loss"].detach()))
    assert losses[-1] < 0.5 * losses[0]
    with torch.no_grad():
        out = model({"image": img})
    best = out["scores"][0, :, 1].argmax()
    from vslam.nn.ops import box_iou

    assert float(box_iou(out["boxes"][0, best][None], GT[0])) > 0.5


def test_freeze_bn_keeps_the_statistics():
    model = tiny().train()
    before = model.neck.backbone.stem.conv.bn.running_mean.clone()
    freeze_bn(model)
    model({"image": torch.rand(2, 3, *SIZE) * 255})
    assert torch.equal(model.neck.backbone.stem.conv.bn.running_mean, before)
