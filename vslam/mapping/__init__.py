"""The map (keyframes, points, covisibility) and local mapping."""

from vslam.mapping.map import KeyFrame, Map, MapPoint

__all__ = ["KeyFrame", "Map", "MapPoint"]
