"""Detector training loss (YOLOv8 recipe): task-aligned assignment, BCE classification, CIoU + DFL box terms.

- Task-aligned assignment: Feng et al., "TOOD: Task-aligned One-stage Object Detection", ICCV 2021 —
  an anchor point inside a ground-truth box is scored t = s^alpha * IoU^beta (s: predicted score of the box's
  class); the top-k per box are positives, and the soft class target is t normalised to the box's best IoU.
- CIoU: Zheng et al., "Distance-IoU Loss", AAAI 2020. DFL: Li et al., "Generalized Focal Loss", NeurIPS 2020.

- Instance masks (a model with a mask head): per positive anchor, BCE between its assembled mask and the mask of
  the box it was assigned to, inside that box, averaged over the box's area (YOLOv8-seg); instances whose label
  has no mask (KITTI boxes, a teacher's boxes) train the box only.

Targets: ``gt_boxes`` (B, M, 4) x1,y1,x2,y2 input pixels, ``gt_labels`` (B, M) int, ``gt_mask`` (B, M) bool
(M: most boxes in one image; padding rows are False). Optional: ``Targets.masks`` (B, M, H/4, W/4) in [0, 1]
with ``masks_valid`` (B, M) bool; ``ignore`` (B, J, 4) regions (KITTI's DontCare) with ``ignore_valid`` (B, J):
an anchor there that no box claims is not pushed towards background.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from vslam.dynamic.model import YoloDetector, box_crop, dist2bbox, make_anchors, mask_outputs, split_outputs


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
    mask: float = 7.5  # YOLOv8-seg's gain of the mask term (its box gain)


@dataclass
class MaskTargets:
    """The optional targets of ``detection_loss`` (shapes in the module docstring)."""

    masks: torch.Tensor | None = None
    masks_valid: torch.Tensor | None = None
    ignore: torch.Tensor | None = None
    ignore_valid: torch.Tensor | None = None


@torch.no_grad()
def assign(scores: torch.Tensor, boxes: torch.Tensor, anchors: torch.Tensor, gt_labels: torch.Tensor,
           gt_boxes: torch.Tensor, gt_mask: torch.Tensor, cfg: LossConfig
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Task-aligned assignment. scores (B,A,C) probabilities, boxes (B,A,4) and anchors (A,2) in pixels.
    -> target boxes (B,A,4) pixels, soft target scores (B,A,C), foreground mask (B,A), index of the assigned
    ground-truth box (B,A) (meaningful where foreground)."""
    B, A, C = scores.shape
    M = gt_boxes.shape[1]
    if M == 0:
        return (torch.zeros_like(boxes), torch.zeros_like(scores), torch.zeros(B, A, dtype=torch.bool, device=scores.device),
                torch.zeros(B, A, dtype=torch.long, device=scores.device))
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
    return t_boxes, t_scores * norm[..., None], fg, idx


def _ignored(anchors_px: torch.Tensor, t: MaskTargets, fg: torch.Tensor) -> torch.Tensor:
    """(B,A) bool: background anchors whose centre lies in an ignore region."""
    if t.ignore is None or t.ignore.shape[1] == 0:
        return torch.zeros_like(fg)
    lt = anchors_px[None, None] - t.ignore[:, :, None, :2]
    rb = t.ignore[:, :, None, 2:] - anchors_px[None, None]
    inside = (torch.cat([lt, rb], -1).amin(-1) > 0) & t.ignore_valid[:, :, None]  # (B,J,A)
    return inside.any(1) & ~fg


def mask_loss(coef: torch.Tensor, proto: torch.Tensor, fg: torch.Tensor, idx: torch.Tensor, gt_boxes: torch.Tensor,
              t: MaskTargets) -> torch.Tensor:
    """Mean over the positive anchors whose assigned box has a mask: BCE inside that box, per box area."""
    if t.masks is None or not fg.any():
        return proto.sum() * 0.0
    has = fg & t.masks_valid.gather(1, idx)
    if not has.any():
        return proto.sum() * 0.0
    total, n = proto.new_zeros(()), 0
    h, w = proto.shape[2:]
    stride = 4.0
    for b in range(fg.shape[0]):  # per image: its prototypes and its boxes
        sel = has[b]
        if not sel.any():
            continue
        j = idx[b, sel]
        boxes = gt_boxes[b, j].to(proto.dtype)
        inside = box_crop(boxes / stride, h, w)
        logits = (coef[b, sel] @ proto[b].reshape(proto.shape[1], -1)).view(-1, h, w)
        bce = F.binary_cross_entropy_with_logits(logits, t.masks[b, j].to(logits.dtype), reduction="none")
        area = inside.sum((1, 2)).clamp(min=1)
        total = total + ((bce * inside).sum((1, 2)) / area).sum()
        n += int(sel.sum())
    return total / max(n, 1)


def detection_loss(model: YoloDetector, feats: list[torch.Tensor], gt_boxes: torch.Tensor, gt_labels: torch.Tensor,
                   gt_mask: torch.Tensor, cfg: LossConfig = LossConfig(),
                   targets: MaskTargets | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss (scalar) and its parts {box, cls, dfl[, mask]} for logging."""
    R = model.cfg.reg_max
    t = targets or MaskTargets()
    reg, cls = split_outputs(model, feats)
    anchors, strides = make_anchors(feats)  # grid units, (A,1)
    B, A, _ = reg.shape
    dist = (reg.view(B, A, 4, R).softmax(-1) * torch.arange(R, dtype=reg.dtype, device=reg.device)).sum(-1)
    pred = dist2bbox(dist, anchors)  # grid units of each anchor's level
    t_boxes, t_scores, fg, idx = assign(cls.detach().sigmoid(), (pred.detach() * strides).to(gt_boxes.dtype),
                                        anchors * strides, gt_labels, gt_boxes, gt_mask, cfg)
    tss = t_scores.sum().clamp(min=1.0)
    ignored = _ignored((anchors * strides).to(gt_boxes.dtype), t, fg)
    if ignored.any():
        bce = F.binary_cross_entropy_with_logits(cls, t_scores.to(cls.dtype), reduction="none")
        loss_cls = (bce * ~ignored[..., None]).sum() / tss
    else:
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
    parts = {"box": float(loss_box.detach()), "cls": float(loss_cls.detach()), "dfl": float(loss_dfl.detach())}
    if model.cfg.masks:
        coef, proto = mask_outputs(model, feats)
        loss_mask = mask_loss(coef, proto, fg, idx, gt_boxes, t)
        total = total + cfg.mask * loss_mask
        parts["mask"] = float(loss_mask.detach())
    return total, parts
