"""Pure torch models: the DAPM network, its settings and parts (never imports Lightning)."""

from dapm_lightning.models.config import AUTHORS_TRAINING, EFFICIENT_NETWORK, PAPER_NETWORK, DAPMConfig
from dapm_lightning.models.dapm import DAPMNet, DAPMOutput, DepthPrediction, InferenceOutput, PosePrediction
from dapm_lightning.models.encoder import Encoder
from dapm_lightning.models.prior import PosePrior, PriorMode, PriorSettings, fuse_pose
from dapm_lightning.models.teacher_forcing import TeacherForcing, predicted_share_at

__all__ = ["AUTHORS_TRAINING", "EFFICIENT_NETWORK", "PAPER_NETWORK", "DAPMConfig", "DAPMNet", "DAPMOutput",
           "DepthPrediction", "Encoder", "InferenceOutput", "PosePrediction", "PosePrior", "PriorMode",
           "PriorSettings", "TeacherForcing", "fuse_pose", "predicted_share_at"]
