"""IGD teacher forcing: the pose fed to the IGD feature blends the true and the predicted pose during training.

The paper raises the predicted share linearly over training until the IGD sees predictions only;
:func:`predicted_share_at` is that schedule and :class:`TeacherForcing` the blend the network applies.
The Lightning callback :class:`~dapm_lightning.training.callbacks.IGDTeacherForcing` only passes the
current share on.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def predicted_share_at(progress: float, *, start_share: float = 0.0, end_share: float = 1.0,
                       start_fraction: float = 0.0, end_fraction: float = 1.0) -> float:
    """Predicted share at ``progress`` in [0, 1] of training: linear from ``start_share`` to ``end_share``.

    The ramp runs between ``start_fraction`` and ``end_fraction`` of training and is flat outside it.
    """
    if not 0.0 <= start_fraction < end_fraction:
        raise ValueError(f"need 0 <= start_fraction < end_fraction, got {start_fraction}, {end_fraction}")
    if not (0.0 <= start_share <= 1.0 and 0.0 <= end_share <= 1.0):  # outside: a pose beyond the true or the predicted
        raise ValueError(f"start_share and end_share are shares of the predicted pose, in [0, 1] (0: the true pose, 1: "
                         f"the prediction), got {start_share}, {end_share}")
    t = min(1.0, max(0.0, (progress - start_fraction) / (end_fraction - start_fraction)))
    return start_share + (end_share - start_share) * t


@dataclass(frozen=True)
class TeacherForcing:
    """The IGD input ``share * predicted + (1 - share) * true`` (normalised poses).

    Args:
        pose_norm_true: ``[B, 4]`` normalised true pose; rows with NaN (images without a pose) keep the prediction.
        predicted_share: weight of the predicted pose in [0, 1].
    """

    pose_norm_true: Tensor
    predicted_share: float

    def blend(self, pose_norm_predicted: Tensor) -> Tensor:
        """``[B, 4]`` predicted normalised pose -> ``[B, 4]`` pose the IGD feature sees."""
        if self.predicted_share >= 1.0:
            return pose_norm_predicted
        known = torch.isfinite(self.pose_norm_true).all(dim=1, keepdim=True)
        true = torch.where(known, self.pose_norm_true, pose_norm_predicted)
        return self.predicted_share * pose_norm_predicted + (1.0 - self.predicted_share) * true
