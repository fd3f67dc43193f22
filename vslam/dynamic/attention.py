"""The attention blocks live in ``vslam.nn.attention`` (shared by the from-scratch detector and the YOLOX-style
one); this name stays for the code and checkpoints' users that import it from here."""

from vslam.nn.attention import ATTENTION, CBAM, ESEA, SE, SpatialAttention, make_attention

__all__ = ["ATTENTION", "CBAM", "ESEA", "SE", "SpatialAttention", "make_attention"]
