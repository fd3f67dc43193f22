"""The YOLOX training loss (Ge et al. 2021, sec. 2.1 "SimOTA"), for fine-tuning the converted public weights.

Per image: candidate anchors are those whose centre lies inside a ground-truth box or within ``center_radius``
strides of its centre; the cost of assigning a candidate to a box is its class BCE + 3 (-log IoU), plus a large
constant outside both regions; each box takes its ``k`` cheapest candidates with k = clamp(sum of its 10 best
IoUs, 1) ("dynamic k"), and an anchor claimed by several boxes goes to the cheapest. Losses, normalised by the
number of assigned anchors: box 1 - IoU^2 (Megvii's IoULoss), objectness BCE on every anchor (1 on the
assigned), class BCE on the assigned with the one-hot target scaled by the IoU (an anchor whose box is off is
asked for a lower score). Megvii also adds an L1 term in the last epochs; it is left out here.

Fine-tuning from the BN-folded export starts with BatchNorm in eval mode (``freeze_bn``): the statistics the
converter wrote (mean 0, variance 1 - eps) are those the folded weights imply, and small CPU batches would
replace them by noisy batch statistics at the first step.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vslam.nn.ops import box_iou, box_iou_paired


def freeze_bn(model: nn.Module) -> nn.Module:
    """Every BatchNorm of ``model`` in eval mode (running statistics kept; its affine weights still train)."""
    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.eval()
    return model


@torch.no_grad()
def simota(boxes: torch.Tensor, cls_logits: torch.Tensor, obj_logits: torch.Tensor, centres: torch.Tensor,
           stride: torch.Tensor, gt_boxes: torch.Tensor, gt_classes: torch.Tensor,
           center_radius: float = 2.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One image: boxes (A, 4) predicted, cls_logits (A, nc), obj_logits (A,), centres (A, 2) anchor points
    (cell index * stride, the grid's corner convention), stride (A,); gt_boxes (G, 4), gt_classes (G,) ->
    (fg (A,) bool, matched gt index (A,) long, IoU of each anchor's box with its gt (A,))."""
    A, G = len(boxes), len(gt_boxes)
    fg = torch.zeros(A, dtype=torch.bool, device=boxes.device)
    if G == 0:
        return fg, torch.zeros(A, dtype=torch.long, device=boxes.device), torch.zeros(A, device=boxes.device)
    c = centres + stride[:, None] / 2  # the cell's centre
    inside_box = ((c[:, None] > gt_boxes[None, :, :2]) & (c[:, None] < gt_boxes[None, :, 2:])).all(-1)  # (A, G)
    gc = (gt_boxes[:, :2] + gt_boxes[:, 2:]) / 2
    r = center_radius * stride[:, None, None]
    inside_ctr = ((c[:, None] > gc[None] - r) & (c[:, None] < gc[None] + r)).all(-1)
    cand = (inside_box | inside_ctr).any(1)
    both = (inside_box & inside_ctr)[cand]
    iou = box_iou(boxes[cand], gt_boxes)  # (C, G)
    p = (cls_logits[cand].sigmoid() * obj_logits[cand, None].sigmoid()).sqrt()  # Megvii's joint score
    target = F.one_hot(gt_classes, cls_logits.shape[1]).float()
    cls_cost = F.binary_cross_entropy(p[:, None].expand(-1, G, -1), target[None].expand(len(p), -1, -1),
                                      reduction="none").sum(-1)
    cost = cls_cost + 3.0 * -torch.log(iou + 1e-8) + 1e5 * (~both)
    # dynamic k: each box takes as many anchors as its 10 best IoUs sum to (at least one)
    k = iou.topk(min(10, len(iou)), 0).values.sum(0).int().clamp(min=1)
    match = torch.zeros_like(cost, dtype=torch.bool)
    for g in range(G):
        match[cost[:, g].topk(int(min(k[g], len(cost))), largest=False).indices, g] = True
    multi = match.sum(1) > 1  # an anchor claimed twice goes to its cheapest box
    if multi.any():
        match[multi] = F.one_hot(cost[multi].argmin(1), G).bool()
    idx = torch.nonzero(cand).squeeze(1)
    chosen = match.any(1)
    fg[idx[chosen]] = True
    gt_of = torch.zeros(A, dtype=torch.long, device=boxes.device)
    gt_of[idx[chosen]] = match[chosen].float().argmax(1)
    ious = torch.zeros(A, device=boxes.device)
    ious[idx[chosen]] = iou[chosen].gather(1, gt_of[idx[chosen]][:, None]).squeeze(1)
    return fg, gt_of, ious


def yolox_loss(out: dict[str, torch.Tensor], targets: list[tuple[torch.Tensor, torch.Tensor]],
               size: tuple[int, int], obj_weight: float = 1.0, box_weight: float = 5.0,
               ignore: list[torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
    """``out``: a YOLOX forward pass (``logits`` (B, A, 5 + nc), ``boxes`` (B, A, 4)) of inputs of ``size`` (h, w);
    ``targets`` per image: (gt boxes (G, 4) input pixels, classes (G,) long) -> {"loss", "box", "obj", "cls",
    "fg"} (Megvii's weights: box 5, objectness and class 1). ``ignore`` per image: (J, 4) regions (KITTI
    DontCare, as COCO crowd boxes): an anchor not assigned to a box whose cell centre lies inside one has no
    objectness loss (neither object nor background)."""
    from vslam.nn.detectors.yolox import STRIDES, grid

    logits, boxes = out["logits"], out["boxes"]
    B = len(logits)
    xy, stride = grid([(size[0] // s, size[1] // s) for s in STRIDES], logits.device)
    stride = stride[:, 0]
    assert len(xy) == logits.shape[1], "size is not the forward pass's input size"
    centres = xy * stride[:, None]
    obj_t = torch.zeros(logits.shape[:2], device=logits.device)
    box_l, cls_l, n_fg = logits.new_zeros(()), logits.new_zeros(()), 0
    for i in range(B):
        gb, gc = targets[i]
        fg, gt_of, ious = simota(boxes[i].detach(), logits[i, :, 5:].detach(), logits[i, :, 4].detach(), centres,
                                 stride, gb, gc)
        if not fg.any():
            continue
        n_fg += int(fg.sum())
        obj_t[i, fg] = 1.0
        iou = box_iou_paired(boxes[i, fg], gb[gt_of[fg]])
        box_l = box_l + (1 - iou ** 2).sum()
        cls_t = F.one_hot(gc[gt_of[fg]], logits.shape[2] - 5).float() * ious[fg, None]
        cls_l = cls_l + F.binary_cross_entropy_with_logits(logits[i, fg, 5:], cls_t, reduction="sum")
    n = max(n_fg, 1)
    obj_w = torch.ones_like(obj_t)
    for i, g in enumerate(ignore or []):
        if len(g):
            c = centres + stride[:, None] / 2
            inside = ((c[:, None] > g[None, :, :2]) & (c[:, None] < g[None, :, 2:])).all(-1).any(1)
            obj_w[i, inside & (obj_t[i] == 0)] = 0.0
    obj_l = F.binary_cross_entropy_with_logits(logits[..., 4], obj_t, weight=obj_w, reduction="sum")
    box_l, obj_l, cls_l = box_l / n, obj_l / n, cls_l / n
    return {"loss": box_weight * box_l + obj_weight * obj_l + cls_l, "box": box_l.detach(), "obj": obj_l.detach(),
            "cls": cls_l.detach(), "fg": torch.tensor(n_fg)}
