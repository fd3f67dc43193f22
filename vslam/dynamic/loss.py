"""Detector training loss (YOLOv8 recipe): task-aligned assignment, BCE classification, CIoU + DFL box terms.

- Task-aligned assignment: Feng et al., "TOOD: Task-aligned One-stage Object Detection", ICCV 2021 —
  an anchor point inside a ground-truth box is scored t = s^alpha * IoU^beta (s: predicted score of the box's
  class); the top-k per box are positives, and the soft class target is t normalised to the box's best IoU.
- CIoU: Zheng et al., "Distance-IoU Loss", AAAI 2020. DFL: Li et al., "Generalized Focal Loss", NeurIPS 2020.

Targets: ``gt_boxes`` (B, M, 4) x1,y1,x2,y2 input pixels, ``gt_labels`` (B, M) int, ``gt_mask`` (B, M) bool
(M: most boxes in one image; padding rows are False).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from vslam.dynamic.model import YoloDetector, dist2bbox, make_anchors, split_outputs


def ciou(b1: torch.Tensor, b2: torch.Tensor, eps: float = 1e-7) -> torch.Tensor:
    """Complete IoU of matching rows (…, 4) x1y1x2y2 -> (…)."""
    w1, h1 = b1[..., 2] - b1[..., 0], (b1[..., 3] - b1[..., 1]).clamp(min=eps)
    w2, h2 = b2[..., 2] - b2[..., 0], (b2[..., 3] - b2[..., 1]).clamp(min=eps)
    iw = (torch.minimum(b1[..., 2], b2[..., 2]) - torch.maximum(b1[..., 0], b2[..., 0])).clamp(min=0)
    ih = (torch.minimum(b1[..., 3], b2[..., 3]) - torch.maximum(b1[..., 1], b2[..., 1])).clamp(min=0)
    inter = iw * ih
    iou = inter / (w1 * h1 + w2 * h2 - inter + eps)
    cw = torch.maximum(b1[..., 2], b2[..., 2]) - torch.minimum(b1[..., 0], b2[..., 0])
    ch = torch.maximum(b1[..., 3], b2[..., 3]) - torch.minimum(b1[..., 1], b2[..., 1])
    c2 = cw**2 + ch**2 + eps
    rho2 = ((b2[..., 0] + b2[..., 2] - b1[..., 0] - b1[..., 2]) ** 2 + (b2[..., 1] + b2[..., 3] - b1[..., 1] - b1[..., 3]) ** 2) / 4
    v = (4 / math.pi**2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


@dataclass(frozen=True)
class LossConfig:
    topk: int = 10
    alpha: float = 0.5
    beta: float = 6.0
    box: float = 7.5  # YOLOv8 default gains
    cls: float = 0.5
    dfl: float = 1.5


@torch.no_grad()
def assign(scores: torch.Tensor, boxes: torch.Tensor, anchors: torch.Tensor, gt_labels: torch.Tensor,
           gt_boxes: torch.Tensor, gt_mask: torch.Tensor, cfg: LossConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Task-aligned assignment. scores (B,A,C) probabilities, boxes (B,A,4) and anchors (A,2) in pixels.
    -> target boxes (B,A,4) pixels, soft target scores (B,A,C), foreground mask (B,A)."""
    B, A, C = scores.shape
    M = gt_boxes.shape[1]
    if M == 0:
        return torch.zeros_like(boxes), torch.zeros_like(scores), torch.zeros(B, A, dtype=torch.bool, device=scores.device)
    lt = anchors[None, None] - gt_boxes[:, :, None, :2]
    rb = gt_boxes[:, :, None, 2:] - anchors[None, None]
    inside = torch.cat([lt, rb], -1).amin(-1) > 1e-9  # (B,M,A)
    valid = inside & gt_mask[:, :, None]
    lab = gt_labels.long().clamp(min=0)
    s = scores.gather(2, lab[:, None, :].expand(B, A, M)).permute(0, 2, 1)  # (B,M,A) score of the gt's class
    iou = ciou(gt_boxes[:, :, None, :].expand(B, M, A, 4), boxes[:, None].expand(B, M, A, 4)).clamp(min=0)
    iou = iou * valid
    metric = s.pow(cfg.alpha) * iou.pow(cfg.beta) * valid
    top = metric.topk(min(cfg.topk, A), dim=-1).indices  # (B,M,k)
    pos = torch.zeros_like(metric, dtype=torch.bool).scatter_(-1, top, True) & valid & (metric > 0)
    multi = pos.sum(1, keepdim=True) > 1  # an anchor claimed by several boxes keeps the best-overlapping one
    best = F.one_hot(iou.argmax(1), M).permute(0, 2, 1).bool()
    pos = torch.where(multi, best & valid, pos)
    fg = pos.any(1)  # (B,A)
    idx = pos.float().argmax(1)  # (B,A) gt index
    t_boxes = gt_boxes.gather(1, idx[..., None].expand(B, A, 4))
    t_labels = lab.gather(1, idx)
    t_scores = F.one_hot(t_labels, C).float() * fg[..., None]
    metric = metric * pos
    norm = (metric * (iou * pos).amax(-1, keepdim=True) / (metric.amax(-1, keepdim=True) + 1e-9)).amax(1)  # (B,A)
    return t_boxes, t_scores * norm[..., None], fg


def detection_loss(model: YoloDetector, feats: list[torch.Tensor], gt_boxes: torch.Tensor, gt_labels: torch.Tensor,
                   gt_mask: torch.Tensor, cfg: LossConfig = LossConfig()) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss (scalar) and its parts {box, cls, dfl} for logging."""
    R = model.cfg.reg_max
    reg, cls = split_outputs(model, feats)
    anchors, strides = make_anchors(feats)  # grid units, (A,1)
    B, A, _ = reg.shape
    dist = (reg.view(B, A, 4, R).softmax(-1) * torch.arange(R, dtype=reg.dtype, device=reg.device)).sum(-1)
    pred = dist2bbox(dist, anchors)  # grid units of each anchor's level
    t_boxes, t_scores, fg = assign(cls.detach().sigmoid(), (pred.detach() * strides).to(gt_boxes.dtype),
                                   anchors * strides, gt_labels, gt_boxes, gt_mask, cfg)
    tss = t_scores.sum().clamp(min=1.0)
    loss_cls = F.binary_cross_entropy_with_logits(cls, t_scores.to(cls.dtype), reduction="sum") / tss
    loss_box = loss_dfl = reg.sum() * 0.0
    if fg.any():
        w = t_scores.sum(-1)[fg]
        tb = (t_boxes / strides)[fg]
        loss_box = ((1.0 - ciou(pred[fg], tb)) * w).sum() / tss
        a = anchors.expand(B, A, 2)[fg]
        target = torch.cat([a - tb[:, :2], tb[:, 2:] - a], -1).clamp(0, R - 1 - 0.01)  # (P,4) side distances
        lo = target.long()
        wl = lo + 1 - target
        logits = reg[fg].view(-1, 4, R)
        ce = F.cross_entropy(logits.reshape(-1, R), lo.view(-1), reduction="none").view(-1, 4) * wl \
            + F.cross_entropy(logits.reshape(-1, R), (lo + 1).view(-1), reduction="none").view(-1, 4) * (1 - wl)
        loss_dfl = (ce.mean(-1) * w).sum() / tss
    total = cfg.box * loss_box + cfg.cls * loss_cls + cfg.dfl * loss_dfl
    return total, {"box": float(loss_box.detach()), "cls": float(loss_cls.detach()), "dfl": float(loss_dfl.detach())}
