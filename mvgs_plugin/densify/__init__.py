"""MVGS's two densification rules, as pure functions: the threshold rule (MVAD) and the
cross-ray boxes (CRD). The controller calls them; adapters receive their results in the
DensifyContext."""

from .crd import (best_windows, boxes_contain, check_boxes, closest_points, cross_ray_boxes, loss_map, top_by_score,
                  window_corners)
from .mvad import camera_axes, mvad_threshold, pair_discrepancy, resolution_threshold

__all__ = ["mvad_threshold", "resolution_threshold", "pair_discrepancy", "camera_axes", "best_windows", "window_corners",
           "closest_points", "cross_ray_boxes", "check_boxes", "boxes_contain", "top_by_score", "loss_map"]
