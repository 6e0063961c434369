"""Depth and pose metrics as ``torchmetrics.Metric`` subclasses, correct under DDP (docs/model.md: their protocols)."""

from dapm_lightning.metrics.depth import (
                                         AUTHORS_DEPTH_METRIC_NAMES,
                                         DEPTH_METRIC_NAMES,
                                         AuthorsDepthMetrics,
                                         DepthMetrics,
                                         per_image_depth_metrics,
)
from dapm_lightning.metrics.pose import AuthorsPoseMetrics, PoseMetrics, auc_of_recall, authors_auc

__all__ = ["AUTHORS_DEPTH_METRIC_NAMES", "DEPTH_METRIC_NAMES", "AuthorsDepthMetrics", "AuthorsPoseMetrics",
           "DepthMetrics", "PoseMetrics", "auc_of_recall", "authors_auc", "per_image_depth_metrics"]
